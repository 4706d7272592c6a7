"""vergence: dynamic vergence control for active stereo vision (Reskó et al.'s five-layer network).

The library never imports zenoh: the services/ package adapts it to the network. The public names below are
imported on first use (PEP 562), so that a process that needs only the settings, the keys or the messages (`vergence
up`, the actuator, the clients) does not load numba and the kernels (about 0.6 s of its start)."""

import importlib
import sys
import types

_PUBLIC = {"features": "network.retina", "BorderError": "network.retina", "correlate": "network.kernel",
           "decide": "network.decide", "Decision": "network.decide", "centre_offset": "network.decide",
           "match": "network.match", "Match": "network.match", "Params": "network.params", "FAITHFUL": "network.params"}

__all__ = [
    "FAITHFUL",
    "BorderError",
    "Decision",
    "Match",
    "Params",
    "centre_offset",
    "correlate",
    "decide",
    "features",
    "match",
]
__version__ = "0.1.0"


class _Package(types.ModuleType):
    """The public names, each imported from its module (in vergence.network) on first use."""

    def __getattr__(self, name: str):
        if name not in _PUBLIC:
            raise AttributeError(f"module 'vergence' has no attribute {name!r}")
        value = getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
        super().__setattr__(name, value)
        return value

    def __dir__(self) -> list[str]:
        return sorted(set(super().__dir__()) | set(__all__))


sys.modules[__name__].__class__ = _Package
