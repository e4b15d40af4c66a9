"""The render settings of the synthetic scene (``data.render``), checked by `locretrieval.config.validated`.

Their defaults live in ``configs/data/synthetic.yaml``; each environment is an
`EnvironmentBuilder` chosen by its ``_target_`` (``data.render.environments``), the one
rendered named by ``data.render.environment``.
"""

from __future__ import annotations

import abc
import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from locretrieval.config import named_parts, require

if TYPE_CHECKING:
    import numpy as np

    from locretrieval.scene.synthetic.world import Environment

CONDITIONS = ("night", "blur", "dynamic", "noise")


class EnvironmentBuilder(abc.ABC):
    """A kind of synthetic scene (the mall, the street). A new one subclasses this, in any
    package, and is chosen by its ``_target_`` (``data.render.environments.<name>``)."""

    @abc.abstractmethod
    def build(self, rng: np.random.Generator, length: float, texture_size: int) -> Environment:
        """A random scene ``length`` metres long along ``x``, its textures ``texture_size`` texels
        square, drawn from ``rng`` (deterministic in it)."""


@dataclass
class Conditions:
    """Independent per-query probabilities of each capture condition (`CONDITIONS`)."""

    night: float
    blur: float
    dynamic: float
    noise: float

    def __post_init__(self) -> None:
        for name in CONDITIONS:
            _require_probability(getattr(self, name), name)


@dataclass
class RenderSettings:
    """The ``data.render`` section (``configs/data/synthetic.yaml`` documents each key): the scene
    (``environment``, a name of ``environments``, ``seed``, ``length``, ``texture_size``), the
    cameras and images, their conditions, and how the renderer runs (``device``, ``workers``)."""

    seed: int
    environment: str
    environments: dict[str, Any] = named_parts(EnvironmentBuilder)
    device: str
    length: float
    width: int
    height: int
    num_database: int
    num_queries: int
    database_fov_deg: float
    query_fov_deg: list[float]
    conditions: Conditions
    database_dynamic: float
    hard_query_fraction: float
    supersampling: int
    texture_size: int
    blur_subframes: int
    noise_std: float
    workers: int

    def __post_init__(self) -> None:
        require(
            self.environment in self.environments,
            "environment",
            f"must be a name of data.render.environments {list(self.environments)}, got {self.environment!r}",
        )
        for key in ("width", "height", "num_database", "supersampling", "blur_subframes", "workers"):
            require(getattr(self, key) >= 1, key, f"must be a positive integer, got {getattr(self, key)}")
        require(self.num_queries >= 0, "num_queries", f"must be >= 0, got {self.num_queries}")
        require(
            self.blur_subframes % 2 == 1,
            "blur_subframes",
            f"must be odd (the middle sub-frame is the written mid-exposure pose), got {self.blur_subframes}",
        )
        size = self.texture_size
        require(size >= 16 and not size & (size - 1), "texture_size", f"must be a power of two >= 16, got {size}")
        require(20.0 <= self.length <= 500.0, "length", f"must be between 20 and 500 metres, got {self.length}")
        require(
            bool(self.query_fov_deg),
            "query_fov_deg",
            "must be a non-empty list of horizontal fields of view in degrees",
        )
        for key, fovs in (("database_fov_deg", [self.database_fov_deg]), ("query_fov_deg", self.query_fov_deg)):
            require(all(10.0 <= fov <= 150.0 for fov in fovs), key, f"must be between 10 and 150 degrees, got {fovs}")
        _require_probability(self.database_dynamic, "database_dynamic")
        _require_probability(self.hard_query_fraction, "hard_query_fraction")
        require(self.noise_std >= 0, "noise_std", f"must be >= 0, got {self.noise_std}")

    @property
    def builder(self) -> EnvironmentBuilder:
        """The `EnvironmentBuilder` of ``environment``."""
        return self.environments[self.environment]

    def record(self) -> dict[str, Any]:
        """The settings as plain data (``synthetic_config.json``, the rendered scene's cache key):
        the environment rendered by its name and its builder's class and parameters, not the others."""
        values = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}
        builder = self.builder
        values["environments"] = {
            self.environment: {
                "_target_": f"{type(builder).__module__}.{type(builder).__qualname__}",
                **(dataclasses.asdict(builder) if dataclasses.is_dataclass(builder) else {}),
            }
        }
        values["conditions"] = dataclasses.asdict(self.conditions)
        return values


def _require_probability(value: float, key: str) -> None:
    require(0.0 <= value <= 1.0, key, f"must be a probability in [0, 1], got {value}")
