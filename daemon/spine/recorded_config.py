"""Configs recorded in older logs, read as today's schema: the flat mapper keys from before the mapper config was
sectioned, moved into their sections (a log's config is what its data was taken with: it stays readable); and the
mapper keys this version no longer knows (renamed or removed tuning), dropped and named, so today's defaults apply.
The sensors, vehicle and recorder sections stay strict: they describe the data, and a key read wrong there would
misread it."""

from __future__ import annotations

from pydantic import BaseModel

from daemon.spine.mapper_config import MapperConfig

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


def known_mapper_keys(data: object) -> tuple[object, list[str]]:
    """The recorded config with the mapper keys today's MapperConfig does not have removed, and their dotted names."""
    if not isinstance(data, dict) or not isinstance(data.get("mapper"), dict):
        return data, []
    dropped: list[str] = []
    return {**data, "mapper": _known(MapperConfig, data["mapper"], "mapper", dropped)}, dropped


def _known(model: type[BaseModel], section: dict, path: str, dropped: list[str]) -> dict:
    kept = {}
    for key, value in section.items():
        field = model.model_fields.get(key) if isinstance(key, str) else None
        if field is None:
            dropped.append(f"{path}.{key}")
            continue
        sub = field.annotation
        if isinstance(value, dict) and isinstance(sub, type) and issubclass(sub, BaseModel):
            value = _known(sub, value, f"{path}.{key}", dropped)
        kept[key] = value
    return kept
