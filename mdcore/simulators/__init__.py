"""Simulators of the case studies: cracked cantilever and five-storey shear building."""

from .beam import tip_deflection
from .shear_building import ShearBuilding, natural_frequencies

__all__ = ["tip_deflection", "natural_frequencies", "ShearBuilding"]
