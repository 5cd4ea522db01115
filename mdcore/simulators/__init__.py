"""Simulators of the case studies: cracked cantilever and five-storey shear building."""

from .beam import tip_deflection as tip_deflection
from .shear_building import ShearBuilding as ShearBuilding
from .shear_building import natural_frequencies as natural_frequencies

__all__ = ["tip_deflection", "natural_frequencies", "ShearBuilding"]
