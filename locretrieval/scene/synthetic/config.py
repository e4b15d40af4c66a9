"""Configuration of the synthetic scene: defaults, merging and validation."""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence
from typing import Any

ENVIRONMENTS = ("mall", "street")
CONDITIONS = ("night", "blur", "dynamic", "noise")

#: Every key of the synthetic data configuration with its default value.
DEFAULT_CONFIG: dict[str, Any] = {
    "seed": 0,  # scene layout, textures, viewpoints, conditions and noise all follow from it
    "environment": "mall",  # "mall" (shop corridor) or "street" (facades, road, sky)
    "device": "cpu",  # torch device of the renderer ("cpu", "cuda", "auto")
    "length": 48.0,  # corridor / street length in metres
    "width": 480,  # image size in pixels (all cameras)
    "height": 360,
    "num_database": 128,  # mapping images: stations x 2 lanes x 4 headings
    "num_queries": 64,
    "database_fov_deg": 70.0,  # horizontal field of view of the mapping camera (PINHOLE)
    "query_fov_deg": [55.0, 65.0],  # one SIMPLE_PINHOLE query camera per value
    "conditions": {"night": 0.25, "blur": 0.2, "dynamic": 0.3, "noise": 0.2},  # per-query probabilities
    "database_dynamic": 0.1,  # probability that a mapping image shows people/vehicles
    "hard_query_fraction": 0.2,  # queries anywhere, any heading, more tilt (not near a mapping view)
    "supersampling": 1,  # s x s colour samples per pixel (textures are mipmapped anyway)
    "texture_size": 256,  # texels per side of every procedural texture (power of two)
    "blur_subframes": 9,  # sub-frames averaged along the exposure of a blurred image (odd)
    "noise_std": 0.03,  # read-noise standard deviation (image range 0..1), plus shot noise
    "workers": 2,  # rendering processes (1 = in this process)
}


def _plain(value: Any) -> Any:
    """Nested mappings/sequences (e.g. OmegaConf containers) as plain dicts and lists."""
    if isinstance(value, Mapping):
        return {str(key): _plain(item) for key, item in value.items()}
    if isinstance(value, Sequence) and not isinstance(value, str):
        return [_plain(item) for item in value]
    return value


def _check_unknown(given: Mapping[str, Any], known: Mapping[str, Any], where: str) -> None:
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise ValueError(f"unknown {where} key(s) {unknown}; known keys: {sorted(known)}")


def resolve_config(config: Mapping[str, Any] | None) -> dict[str, Any]:
    """The full configuration: ``config`` over :data:`DEFAULT_CONFIG`, validated.

    ``config`` may be any mapping (a dict or an OmegaConf ``DictConfig``); missing keys take
    their defaults, unknown keys are an error naming them.
    """
    given = _plain(config or {})
    _check_unknown(given, DEFAULT_CONFIG, "synthetic data config")
    resolved = copy.deepcopy(DEFAULT_CONFIG)
    conditions = given.pop("conditions", {})
    _check_unknown(conditions, DEFAULT_CONFIG["conditions"], "synthetic data 'conditions'")
    resolved.update(given)
    resolved["conditions"].update(conditions)
    _validate(resolved)
    return resolved


def _validate(config: dict[str, Any]) -> None:
    def fail(key: str, message: str) -> None:
        raise ValueError(f"synthetic data config: {key}={config[key]!r} {message}")

    if config["environment"] not in ENVIRONMENTS:
        fail("environment", f"is not one of {list(ENVIRONMENTS)}")
    for key in ("width", "height", "num_database", "supersampling", "blur_subframes", "workers"):
        if not isinstance(config[key], int) or config[key] < 1:
            fail(key, "must be a positive integer")
    if config["num_queries"] < 0:
        fail("num_queries", "must be >= 0")
    if config["blur_subframes"] % 2 == 0:
        fail("blur_subframes", "must be odd (the middle sub-frame is the written mid-exposure pose)")
    size = config["texture_size"]
    if not isinstance(size, int) or size < 16 or size & (size - 1):
        fail("texture_size", "must be a power of two >= 16")
    if not 20.0 <= float(config["length"]) <= 500.0:
        fail("length", "must be between 20 and 500 metres")
    fovs = config["query_fov_deg"]
    if not isinstance(fovs, list) or not fovs:
        fail("query_fov_deg", "must be a non-empty list of horizontal fields of view in degrees")
    for fov in [config["database_fov_deg"], *fovs]:
        if not 10.0 <= float(fov) <= 150.0:
            raise ValueError(f"synthetic data config: field of view {fov!r} must be between 10 and 150 degrees")
    probabilities = {f"conditions.{k}": v for k, v in config["conditions"].items()}
    probabilities["database_dynamic"] = config["database_dynamic"]
    probabilities["hard_query_fraction"] = config["hard_query_fraction"]
    for key, value in probabilities.items():
        if not 0.0 <= float(value) <= 1.0:
            raise ValueError(f"synthetic data config: {key}={value!r} must be a probability in [0, 1]")
    if float(config["noise_std"]) < 0:
        fail("noise_std", "must be >= 0")
