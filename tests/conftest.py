"""Headless rendering for every test: pyvista off screen, matplotlib Agg."""

import os

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
os.environ.setdefault("MPLBACKEND", "Agg")

import matplotlib  # noqa: E402

matplotlib.use("Agg")

import pyvista  # noqa: E402

pyvista.OFF_SCREEN = True
