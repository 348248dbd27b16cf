"""Pictures of a registration, built on the solver's per-iteration callback (the solver never plots).

Needs the ``viz`` extra (``pip install 'esmicp[viz]'``: matplotlib and plotly), imported only when a
picture is drawn. Every function returns the figure object (a matplotlib ``Figure`` or
``FuncAnimation``, a plotly ``Figure``), for notebooks; the ``write_*`` helpers save them atomically.
"""

from ._deps import require
from .animate import animate, animation_figure, write_animation
from .files import save_figure
from .heatmap import heatmap, heatmap_figure
from .scans import merged_scans_figure
from .inputs import builtin_pair, downsample, farthest_point_subset, moved_copy
from .similarity import similarity_matrix
from .trace import RegistrationTrace, fixed_trace, trace_registration
from .view import (
    display_indices,
    display_subset,
    scatter_trace,
    scene_camera,
    view,
    view_figure,
    view_html,
    view_page,
    write_view,
)

__all__ = [
    "RegistrationTrace",
    "display_indices",
    "display_subset",
    "fixed_trace",
    "require",
    "scatter_trace",
    "animate",
    "animation_figure",
    "builtin_pair",
    "downsample",
    "farthest_point_subset",
    "heatmap",
    "heatmap_figure",
    "merged_scans_figure",
    "moved_copy",
    "save_figure",
    "scene_camera",
    "similarity_matrix",
    "trace_registration",
    "view",
    "view_figure",
    "view_html",
    "view_page",
    "write_animation",
    "write_view",
]
