"""VRScroll twin: device spec, MuJoCo model and simulation, MorphPatch approximation."""

__version__ = "0.1.0"
