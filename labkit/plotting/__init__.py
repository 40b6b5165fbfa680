"""Plot helpers. Each takes an optional target (``ax`` or ``plotter``) and returns it.

Topic submodules: ``labkit.plotting.sphere``, ``.ransac``, ``.clouds``,
``.registration``, ``.consensus``. Shared constants live in ``_style``.
"""

from ._style import COLORS, POINT_SIZE, new_plotter, screenshot, show_render, show_scale

__all__ = ["COLORS", "POINT_SIZE", "new_plotter", "screenshot", "show_render", "show_scale"]
