"""The model-free QoS features (``held_history``) and the labels of the learned QoS rows.

A model-free QoS policy sees ``(y_{t-1}, zeta_{t-1})`` and what their history gives without a
model; the shipped stage-C/D policies read ``predictor_std`` (a Kalman replica at the edge)
and are labelled hybrid.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import codesign_mb.adaptation.model_free_features as mff
from codesign_mb.adaptation.learned import make_features
from codesign_mb.adaptation.model_free_features import HeldHistoryFeature
from codesign_mb.core.registry import ComponentSpec, PlantSpec, make_plant, resolve_checkpoint
from codesign_mb.studies.table_rows import (
    HYBRID_CODESIGN_ROW,
    MODEL_FREE_CODESIGN_ROW,
    all_rows,
    model_free_rows,
    qos_features_stack,
    stack_of,
)


def test_model_free_features_import_no_estimator() -> None:
    """The module imports numpy and typing only; building and running the features on a plant
    loads no estimator or rollout code (the role's kinds modules register names only), and the
    features hold numbers only (no replica)."""
    tree = ast.parse(Path(mff.__file__).read_text())
    imported = {
        (n.module or "") if isinstance(n, ast.ImportFrom) else a.name
        for n in ast.walk(tree)
        if isinstance(n, ast.Import | ast.ImportFrom)
        for a in n.names
    }
    assert imported <= {"__future__", "typing", "numpy", "numpy.typing"}
    script = (
        "import sys, numpy as np\n"
        "from codesign_mb.core.registry import PlantSpec, make_plant, create\n"
        "env = make_plant(PlantSpec('toy'))\n"
        "f = create('qos_feature', 'held_history', env)\n"
        "f.reset(); [f(np.zeros(6), a) for a in (0, 1, 0, 2)]\n"
        "registration = {'codesign_mb.rollout', 'codesign_mb.rollout.kinds'}\n"
        "bad = [m for m in sys.modules if m.startswith(('codesign_mb.estimation', "
        "'codesign_mb.rollout', 'codesign_mb.adaptation.planner')) and m not in registration]\n"
        "held = {type(v).__module__.split('.')[0] for v in vars(f).values()}\n"
        "print(type(f).__module__, bad, sorted(held))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=120
    )
    module, bad, held = out.stdout.strip().split(" ", 2)
    assert (module, bad) == ("codesign_mb.adaptation.model_free_features", "[]")
    assert set(json.loads(held.replace("'", '"'))) <= {"builtins", "numpy"}  # no replica held


def test_held_history_rate_is_the_displacement_over_the_stamps() -> None:
    """An object at constant velocity, packets lost and delayed: the feature's rate is the
    velocity (independent of loss and latency), the lift its height gain."""
    v = np.array([0.0, 0.3, 0.0])
    dt, horizon = 0.04, 50
    f = HeldHistoryFeature(slice(0, 3), control_period_s=dt, horizon=horizon, speed_scale_mps=0.5)
    f.reset()
    rng = np.random.default_rng(0)
    last = 0
    for t in range(horizon):
        if rng.random() < 0.5:  # a packet of step t - 2 arrives (latency 2), else held
            last = max(last, t - 2)
        age = t - last
        held = np.array([0.5, 0.0, 0.1]) + v * dt * last
        out = f(held, age)
        assert out[0] == pytest.approx(t / horizon)
    np.testing.assert_allclose(out[1:4], v / 0.5, atol=1e-9)
    assert out[4] == pytest.approx(0.0)
    assert f(np.array([0.5, 0.0, 0.2]), 0)[4] == pytest.approx(0.1 / 0.05)


def test_held_history_is_selectable_by_kind() -> None:
    env = make_plant(PlantSpec("toy"))
    features = make_features("held_history", env)
    assert isinstance(features, HeldHistoryFeature) and features.dim == 5
    assert features.horizon == env.unwrapped.horizon


def test_shipped_codesign_qos_is_labelled_hybrid() -> None:
    """Every learned QoS row whose checkpoint exists says "hybrid" in its name exactly when
    its recorded features are model-based; the shipped stage-D policy is one."""
    qos = ComponentSpec("learned", "checkpoints/stage_d/qos")
    meta = json.loads((resolve_checkpoint(qos.checkpoint) / "qos_policy.json").read_text())
    assert meta["features"]["kind"] == "predictor_std"
    assert qos_features_stack(qos) == "hybrid"
    rows = {r.name: r for r in (*model_free_rows(), *all_rows())}
    assert stack_of(rows[HYBRID_CODESIGN_ROW]) == "hybrid"
    assert stack_of(rows[MODEL_FREE_CODESIGN_ROW]) == "model-free"
    checked = 0
    for row in rows.values():
        if row.qos.kind != "learned" or row.controller.kind != "sac":
            continue  # the learned QoS of the learned stack (MPC + SAC QoS is model-based)
        try:
            resolve_checkpoint(str(row.qos.checkpoint))
        except ValueError:
            assert "hybrid" not in row.name  # not there: nothing says it is a hybrid
            continue
        checked += 1
        is_hybrid = qos_features_stack(row.qos) == "hybrid"
        assert ("hybrid" in row.name) == is_hybrid, row.name
        assert stack_of(row) == ("hybrid" if is_hybrid else "model-free")
    assert checked >= 2


def test_cli_qos_features_option() -> None:
    from codesign_mb.cli.train import stage_config

    kw = {"assignments": [], "seed": None, "steps": None, "estimator": None}
    assert stage_config("c", None, qos_features="held_history", **kw).features == "held_history"
    assert stage_config("c", None, qos_features="none", **kw).features is None
    assert stage_config("d", None, qos_features="held_history", **kw).qos.features == (
        "held_history"
    )
    with pytest.raises(ValueError, match="stages c and d only"):
        stage_config("b", None, qos_features="held_history", **kw)
    with pytest.raises(ValueError, match="must be none or one of"):
        stage_config("c", None, qos_features="kalman", **kw)


def test_stage_c_trains_a_model_free_qos_policy(tmp_path: Path) -> None:
    """``codesign train c --qos-features held_history`` on the toy plant: the policy records
    its features, is rebuilt with them, and its row is model-free."""
    from codesign_mb.adaptation.learned import LearnedQosPolicy
    from codesign_mb.stages.dual_ascent import DualAscent
    from codesign_mb.stages.stage import StageRun
    from codesign_mb.stages.stage_c import StageCConfig, train_stage_c
    from codesign_mb.stages.training import SacSpec

    toy = PlantSpec("toy", {"horizon": 30})
    config = StageCConfig(
        plant=toy,
        controller=ComponentSpec("toy_pick"),
        estimator=ComponentSpec("none"),
        features="held_history",
        sac=SacSpec(net_arch=(16, 16), buffer_size=1_000, batch_size=16, learning_starts=30),
        total_steps=100,
        chunk_steps=100,
        eval_episodes=0,
        dual=DualAscent(every_episodes=1),
    )
    train_stage_c(config, StageRun(tmp_path / "c", tmp_path / "work"))
    assert LearnedQosPolicy.read_meta(tmp_path / "c")["features"]["kind"] == "held_history"
    env = make_plant(toy)
    policy = LearnedQosPolicy.from_env(env, tmp_path / "c")
    assert isinstance(policy.features, HeldHistoryFeature)
    assert policy.interface.feature_dim == HeldHistoryFeature.dim
    policy.reset()
    assert 0.0 <= policy.request(np.zeros(6), 0).reliability <= 1.0
    qos = ComponentSpec("learned", str(tmp_path / "c"))
    assert qos_features_stack(qos) == "model-free"
