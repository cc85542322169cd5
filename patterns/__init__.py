"""Pattern sets: heuristic families, the learnable parameterisation, pattern files and display frames.

Pure generators and file formats; imports ``capture_sim`` only (DESIGN section 6 and 7).
"""
from patterns.contact_sheet import contact_sheet_figure, save_contact_sheet
from patterns.export import columns_mirrored, export_frames, import_frames, render_frame, superpixel_boundaries
from patterns.families import (
    DEFAULT_SHARPNESS,
    FAMILIES,
    PRESETS,
    Family,
    Parameter,
    bounds,
    default_vector,
    get_family,
    make_patterns,
)
from patterns.io import check_patterns_match_rig, load_patterns, save_patterns, validate_patterns
from patterns.parameterization import logits_to_patterns, patterns_to_logits

__all__ = [
    "DEFAULT_SHARPNESS",
    "FAMILIES",
    "PRESETS",
    "Family",
    "Parameter",
    "bounds",
    "check_patterns_match_rig",
    "columns_mirrored",
    "contact_sheet_figure",
    "default_vector",
    "export_frames",
    "get_family",
    "import_frames",
    "load_patterns",
    "logits_to_patterns",
    "make_patterns",
    "patterns_to_logits",
    "render_frame",
    "save_contact_sheet",
    "save_patterns",
    "superpixel_boundaries",
    "validate_patterns",
]
