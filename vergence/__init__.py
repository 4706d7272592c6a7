"""vergence: dynamic vergence control for active stereo vision (Reskó et al.'s five-layer network).

The library never imports zenoh: the services/ package adapts it to the network."""

from .decide import Decision, centre_offset, decide
from .kernel import correlate
from .match import Match, match
from .params import FAITHFUL, Params
from .retina import BorderError, features

__all__ = ["features", "correlate", "decide", "match", "Params", "Match", "Decision", "FAITHFUL",
           "BorderError", "centre_offset"]
__version__ = "0.1.0"
