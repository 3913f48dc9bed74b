"""The bottom layer: statistics against theory, seed sets, the registry, the process pool."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest

from codesign_mb.core import registry
from codesign_mb.core.registry import ComponentSpec, PlantSpec
from codesign_mb.core.seeds import SEED_SETS, episode_seeds, seed_set
from codesign_mb.core.stats import bootstrap_interval, wilson_interval
from codesign_mb.evaluation import pool


def test_bootstrap_interval_of_a_mean_matches_the_normal_theory() -> None:
    rng = np.random.default_rng(7)
    sample = rng.normal(3.0, 2.0, size=400)
    low, high = bootstrap_interval(sample, resamples=4000, seed=1)
    half = 1.96 * sample.std(ddof=1) / math.sqrt(sample.size)
    assert low < sample.mean() < high
    assert (high - low) / 2 == pytest.approx(half, rel=0.1)
    assert bootstrap_interval([0.5, 0.5, 0.5]) == (0.5, 0.5)
    with pytest.raises(ValueError, match="at least 2"):
        bootstrap_interval([1.0])


def test_wilson_interval_is_exact_at_the_edges() -> None:
    assert wilson_interval(100, 100)[1] == 1.0 and wilson_interval(0, 100)[0] == 0.0
    assert wilson_interval(100, 100)[0] == pytest.approx(0.963, abs=5e-4)


def test_seed_sets_are_named_and_disjoint_streams() -> None:
    assert set(SEED_SETS) == {"dev", "test"}
    dev, test = episode_seeds(seed_set("dev"), 100), episode_seeds(seed_set("test"), 100)
    assert not set(dev) & set(test)
    with pytest.raises(ValueError, match="seed set must be one of test, dev"):
        seed_set("train")


def test_one_registry_builds_every_role_by_kind() -> None:
    assert set(registry.roles()) == {
        "controller",
        "estimator",
        "qos",
        "qos_feature",
        "plant",
        "perception",
        "linear_plant",
        "allocator",
        "stage",
    }
    assert "none" in registry.kinds("estimator") and "plain" not in registry.kinds("estimator")
    toy = registry.make_plant(PlantSpec("toy", {"belt_speed_mps": 0.3}))
    assert toy.config.belt_speed_mps == 0.3
    qos = registry.build("qos", ComponentSpec("static", options={"reliability": 0.4}), toy)
    assert qos.reliability == 0.4
    rule = registry.build("qos", ComponentSpec("rule", options={"threshold_m": 0.02}), toy)
    assert rule.threshold_m == 0.02
    with pytest.raises(ValueError, match="unknown allocator kind 'edf'"):
        registry.create("allocator", "edf")
    with pytest.raises(ValueError, match="role must be one of"):
        registry.kinds("robot")
    with pytest.raises(ValueError, match="needs a checkpoint"):
        registry.factory("controller", ComponentSpec("sac"))


def test_kinds_are_registered_at_the_edges_where_import_linter_sees_them() -> None:
    """Each kind is registered by a kinds module of the package its factory lives in, and that
    module imports the factory's module (for type checking): grimp, import-linter's graph, has
    the edge, so the layer contracts check it; core names no package above it."""
    import importlib.metadata

    import grimp

    graph = grimp.build_graph("codesign_mb", include_external_packages=False)
    entries = importlib.metadata.entry_points(group=registry.ENTRY_POINT_GROUP)
    modules = {e.name.partition(".")[0]: [] for e in entries}
    for e in entries:
        modules[e.name.partition(".")[0]].append(e.value)
    checked = 0
    for role, owners in modules.items():
        for name in registry.kinds(role):
            found = registry.kind(role, name)
            targets = [found.target, *([found.config] if found.config else [])]
            for target in targets:
                module = target.partition(":")[0]
                importers = [
                    m for m in owners if graph.direct_import_exists(importer=m, imported=module)
                ]
                assert importers, (role, name, module, owners)
                package = importers[0].rsplit(".", 1)[0]
                assert module.startswith(package + "."), (role, name, module)
                assert callable(registry.resolve(target)) or isinstance(
                    registry.resolve(target), type
                )
                checked += 1
    assert checked >= 39
    core = {m for m in graph.modules if m.startswith("codesign_mb.core")}
    above = {m for m in graph.modules if not m.startswith("codesign_mb.core")} - {"codesign_mb"}
    assert not any(graph.direct_import_exists(importer=c, imported=a) for c in core for a in above)
    with pytest.raises(ValueError, match="registered twice"):
        registry.register("qos", {"static": registry.Kind("codesign_mb.adaptation.base:RandomQos")})


def _square(x: int) -> int:
    return x * x


def _dies_once(marker: str, x: int) -> int:
    # The first call of task 0 kills its worker process (as an OOM kill would).
    if x == 0 and not Path(marker).exists():
        Path(marker).touch()
        os._exit(1)
    return x + 1


def test_pool_runs_every_task_in_process_and_in_workers() -> None:
    tasks = [(i,) for i in range(6)]
    assert sorted(pool.imap(_square, tasks, workers=1)) == [(i, i * i) for i in range(6)]
    assert sorted(pool.imap(_square, tasks, workers=2)) == [(i, i * i) for i in range(6)]


def test_pool_reruns_the_tasks_of_a_dead_worker(tmp_path: Path) -> None:
    marker = str(tmp_path / "died")
    with pytest.warns(RuntimeWarning, match="worker process died"):
        results = dict(pool.imap(_dies_once, [(marker, i) for i in range(4)], workers=2))
    assert results == {i: i + 1 for i in range(4)}


def test_results_record_provenance_and_checkpoint_digests(tmp_path: Path) -> None:
    import json

    import pandas as pd

    from codesign_mb.core.results import file_digest, write_results

    weights = tmp_path / "ckpt"
    weights.mkdir()
    (weights / "model.zip").write_bytes(b"weights v1")
    paths = write_results(
        tmp_path / "out",
        table=pd.DataFrame({"x": [1, 2]}),
        config={"a": 1},
        name="t",
        checkpoints={"stage_a": weights},
    )
    meta = json.loads(paths["json"].read_text())["provenance"]
    assert meta["checkpoints"] == {"stage_a": file_digest(weights)}
    assert "numpy" in meta["versions"] and "commit" in meta
    before = file_digest(weights)
    (weights / "model.zip").write_bytes(b"weights v2")
    assert file_digest(weights) != before
