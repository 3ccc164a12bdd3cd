"""The ball-screw thermal simulator: the one place where the physics lives.

* :mod:`.parts`: geometry, material, the seed 000 core parameters, numerics, housings;
* :mod:`.kernels`: the finite-difference integrators (seed 000 §3.1);
* :mod:`.model`: core physics composed with effects (seed 000 §3.1, §4.1);
* :mod:`.prepared`: what drives a run (the motion on the fine grid), prepared once;
* :mod:`.history`: the temperature field of a run and the error read off it (seed 000 §3.2, §2.2);
* :mod:`.effects`: the canonical effect library; :mod:`.open_terms`: the open-ended terms;
  :mod:`.registry`: either by id, and the effects of a config;
* :mod:`.duty`, :mod:`.instruments`, :mod:`.scenario`: duty cycles, sensors and
  interferometer, and the config -> dataset pipeline.
"""

from .effects import EFFECTS, Effect
from .history import ThermalHistory
from .model import Motion, ScrewThermalModel
from .parts import CoreParams, Housing, Material, Numerics, Screw
from .registry import effects_from_config, make_effect

__all__ = [
    "EFFECTS", "CoreParams", "Effect", "Housing", "Material", "Motion", "Numerics", "Screw",
    "ScrewThermalModel", "ThermalHistory", "effects_from_config", "make_effect",
]  # fmt: skip
