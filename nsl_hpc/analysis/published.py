"""The study's published laws (conf/published_laws.yaml) beside a sweep's own: b, M, last slope, breaks and
the margin of the published law on our envelope."""

import json
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from omegaconf import OmegaConf

from nsl_hpc.analysis.bootstrap import last_slope
from nsl_hpc.analysis.broken_law import NSLFit, lower_envelope
from nsl_hpc.config import config_dir, plain

KEY = ("system", "arch", "resource", "metric")
PUBLISHED_FILE = "published_laws.yaml"


@dataclass(frozen=True)
class PublishedLaw:
    """One law of the paper: its parameters, margin M, breaks b, resource range and place in the paper."""

    law: NSLFit
    margin: float
    b: int
    resource_range: tuple[float, float]
    where: str

    @property
    def last_slope(self) -> float:
        return float(last_slope(self.law.parameters()))


def key_of(entry: Mapping[str, Any]) -> tuple[str, ...]:
    return tuple(entry[k] for k in KEY)


@cache
def published_data() -> dict[str, Any]:
    """conf/published_laws.yaml as plain data, read once."""
    return plain(OmegaConf.load(config_dir() / PUBLISHED_FILE))


@cache
def resource_columns() -> dict[str, str]:
    """The results column of each resource (conf/nsl/default.yaml): compute -> flops, data -> train_points..."""
    resources = OmegaConf.load(config_dir() / "nsl" / "default.yaml").resources
    return {name: entry.column for name, entry in resources.items()}


@cache
def published_systems() -> dict[str, str]:
    """Our systems whose published laws are another system's (``same_laws`` in the file: the paper's
    Wiener-Hammerstein laws beside both Wiener-Hammerstein data sets), each -> that system."""
    return dict(published_data().get("same_laws") or {})


def published_key(key: tuple[str, ...]) -> tuple[str, ...]:
    """``key`` (system, arch, resource, metric) under the system whose published laws it shares."""
    return (published_systems().get(key[0], key[0]), *key[1:])


def published_law(key: tuple[str, ...]) -> PublishedLaw | None:
    """The published law of (system, arch, resource, metric), None where the paper publishes none."""
    return published_laws().get(published_key(key))


@cache
def published_laws() -> dict[tuple[str, ...], PublishedLaw]:
    """Every published law by (system, arch, resource, metric)."""
    data = published_data()
    laws = {}
    for entry in data["laws"]:
        law = NSLFit(entry["alpha"], entry["beta"], entry["delta0"], [tuple(b) for b in entry["breaks"]],
                     entry["M"], np.empty(0), np.empty(0))
        laws[key_of(entry)] = PublishedLaw(law, entry["M"], entry["b"], tuple(entry["range"]), entry["where"])
    return laws


@cache
def published_margins_by_b() -> dict[tuple[str, ...], dict[int, float]]:
    """Published margins per b where the paper gives no formula (its appendix on choosing b)."""
    data = published_data()
    return {key_of(entry): {int(b): m for b, m in entry["margins"].items()} for entry in data["margins_by_b"]}


def comparison(key: tuple[str, ...], resources: np.ndarray, errors: np.ndarray, K: int) -> dict[str, Any]:
    """The paper_* columns of one NSL: the published law's b, M, last slope, breaks (JSON list of sigma_i),
    resource range of the study's grid (JSON [low, high]), place, and its margin on our Definition 1 envelope
    (``paper_margin_on_ours``); None where the paper publishes none."""
    columns: dict[str, Any] = {"paper_b": None, "paper_margin": None, "paper_last_slope": None,
                               "paper_breaks": None, "paper_margin_on_ours": None, "paper_where": None,
                               "paper_margins_by_b": None, "paper_range": None}
    if published_key(key) in published_margins_by_b():
        columns["paper_margins_by_b"] = json.dumps(published_margins_by_b()[published_key(key)])
    published = published_law(key)
    if published is None:
        return columns
    grid_r, grid_e = lower_envelope(resources, errors, K, "step")
    on_ours = float(np.mean((np.log(published.law.predict(grid_r)) - np.log(grid_e)) ** 2))
    return columns | {"paper_b": published.b, "paper_margin": published.margin,
                      "paper_last_slope": published.last_slope,
                      "paper_breaks": json.dumps([sigma for sigma, _, _ in published.law.breaks]),
                      "paper_margin_on_ours": on_ours, "paper_where": published.where,
                      "paper_range": json.dumps(list(published.resource_range))}


def step_envelope_at(resources: np.ndarray, errors: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Definition 1's step envelope E(r) = min { e_i : r_i <= r } at each resource of ``at`` (NaN where no
    outcome lies at or below it); resources, errors (n,), at (m,) -> (m,)."""
    order = np.argsort(resources)
    running = np.minimum.accumulate(errors[order])
    index = np.searchsorted(resources[order], at, side="right") - 1
    return np.where(index >= 0, running[np.maximum(index, 0)], np.nan)


def gap_to_published(key: tuple[str, ...], resources: np.ndarray, errors: np.ndarray,
                     at: np.ndarray) -> np.ndarray:
    """Our step envelope over the published law of ``key`` (system, arch, resource, metric) at ``at`` (m,)."""
    published = published_law(key)
    if published is None:
        raise KeyError(f"the paper publishes no {'/'.join(key)} law")
    return step_envelope_at(resources, errors, at) / published.law.predict(at)
