"""Configs recorded in older logs, read as today's schema: the flat mapper keys from before the mapper config was
sectioned, moved into their sections (a log's config is what its data was taken with: it stays readable)."""

from __future__ import annotations

# The flat mapper keys of configs recorded before the mapper config was sectioned -> their section and key.
_FLAT_MAPPER_KEYS = {
    "mesh_side_m": ("mesh", "side_m"), "corridor_half_width_m": ("mesh", "corridor_half_width_m"),
    "window_before_m": ("windows", "before_m"), "window_after_m": ("windows", "after_m"),
    **{k: ("model", k) for k in ("colour_code_dim", "positional_encoding_dim", "elevation_mlp_layers",
                                 "elevation_mlp_width", "colour_mlp_layers", "colour_mlp_width", "seed")},
    **{k: ("faithful_fit", k) for k in ("learning_rates", "loss_weights", "epochs", "batch_size")},
    "keyframe_spacing_m": ("inputs", "keyframe_spacing_m"), "threads": ("runtime", "torch_threads_faithful_fit"),
}


def sectioned_recorded_config(data: object) -> object:
    """A config recorded in a log before the mapper config was sectioned, with its flat mapper keys moved into
    their sections (the log's config is what its data was taken with: it stays readable). Others unchanged."""
    if not isinstance(data, dict) or not isinstance(data.get("mapper"), dict):
        return data
    mapper = dict(data["mapper"])
    for flat, (section, key) in _FLAT_MAPPER_KEYS.items():
        if flat in mapper:
            value = mapper.pop(flat)
            mapper[section] = {**(mapper.get(section) or {}), key: value}
    return {**data, "mapper": mapper}
