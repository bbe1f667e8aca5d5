"""MorphPatch: target shapes and their fields (SDF, curvature, HCEVF), the proxy's sample points,
the approximation of a target by the device, surface metrics on the exact mesh, and pen
redirection over the morphed device.

Pure geometry on numpy/scipy/libigl: may import `twin.device` and `twin.perception`; never
MuJoCo, the simulation or the link.
"""
