"""The ball-screw thermal simulator: the one place where the physics lives.

* :mod:`.parts`: geometry, material, the seed 000 core parameters, numerics, housings;
* :mod:`.kernels`: the finite-difference integrators (seed 000 §3.1);
* :mod:`.model`: core physics composed with effects, error read-out (seed 000 §3.2, §2.2);
* :mod:`.effects`: the canonical effect library;
* :mod:`.duty`, :mod:`.instruments`, :mod:`.scenario`: duty cycles, sensors and
  interferometer, and the config -> dataset pipeline.
"""

from .effects import EFFECTS, Effect, effects_from_config, make_effect
from .model import Motion, ScrewThermalModel, ThermalHistory
from .parts import CoreParams, Housing, Material, Numerics, Screw

__all__ = [
    "EFFECTS", "CoreParams", "Effect", "Housing", "Material", "Motion", "Numerics", "Screw",
    "ScrewThermalModel", "ThermalHistory", "effects_from_config", "make_effect",
]  # fmt: skip
