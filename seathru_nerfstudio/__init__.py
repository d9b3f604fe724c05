"""SeaThru-NeRF for nerfstudio: neural radiance fields in scattering media (water, fog)."""

__version__ = "0.1.0"
