"""Pictures and plots of the twin (pyvista scenes, matplotlib charts)."""
