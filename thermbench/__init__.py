"""thermbench: model and compensate the thermal error of CNC ball-screw feed axes.

Data flows one way: dataset files -> validated dataset (:mod:`thermbench.data`)
-> (preprocess) -> model -> predictions/metrics -> tracking/report/export.
The physics (seed 000 finite-difference ball-screw model and its effects) lives
in :mod:`thermbench.sim`.
"""

__version__ = "0.1.0"

from . import _moved

_moved.install()  # old module names (thermbench.benchmark, ...) keep working for one release
