"""vergence: dynamic vergence control for active stereo vision (Reskó et al.'s five-layer network).

The library never imports zenoh: the services/ package adapts it to the network. The public names below are
imported on first use (PEP 562), so that a process that needs only the settings, the keys or the messages (`vergence
up`, the actuator, the clients) does not load numba and the kernels (about 0.6 s of its start)."""

import importlib
import sys
import types

_PUBLIC = {"features": "retina", "BorderError": "retina", "correlate": "kernel", "decide": "decide",
           "Decision": "decide", "centre_offset": "decide", "match": "match", "Match": "match", "Params": "params",
           "FAITHFUL": "params"}

__all__ = ["features", "correlate", "decide", "match", "Params", "Match", "Decision", "FAITHFUL",
           "BorderError", "centre_offset"]
__version__ = "0.1.0"


class _Package(types.ModuleType):
    """`vergence.decide` and `vergence.match` are the functions, as when they were imported eagerly: the import
    system's binding of the submodules of the same names to the package is not kept."""

    def __setattr__(self, name: str, value) -> None:
        if name in ("decide", "match") and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)

    def __getattr__(self, name: str):
        if name not in _PUBLIC:
            raise AttributeError(f"module 'vergence' has no attribute {name!r}")
        value = getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
        super().__setattr__(name, value)
        return value

    def __dir__(self) -> list[str]:
        return sorted(set(super().__dir__()) | set(__all__))


sys.modules[__name__].__class__ = _Package
