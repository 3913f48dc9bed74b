"""The shared WiFi cell as N ``Link``s: lockstep, deadlines, determinism, errors."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from scipy.stats import binomtest

from codesign_mb.adaptation.base import StaticQos
from codesign_mb.estimation.base import PassThroughEstimator
from codesign_mb.network import Link, LinkObservationWrapper, QosRequest
from codesign_mb.rollout import rollout_shared
from codesign_mb.wifi import ChannelConfig, SharedChannel, WifiConfig, WifiLink
from codesign_mb.wifi.channel import frame_delivery_probability
from codesign_mb.wifi.mac import MacTiming

CELL = WifiConfig(
    channel=ChannelConfig(fixed_mcs=1, rician_k_db=math.inf),
    mac=MacTiming(legacy_rate_mbps=6.0),
)


class Drift(gym.Env):
    """A scalar that drifts by one per step; the robot tracks it (success if within 3)."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float64)
    action_space = gym.spaces.Box(-np.inf, np.inf, shape=(1,), dtype=np.float64)
    remote_slice = slice(1, 2)
    horizon = 30

    def remote_prior(self):
        return np.zeros(1)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.robot, self.t = 0.0, 0.0, 0
        return np.array([self.robot, self.x]), {"success": False}

    def step(self, action):
        self.robot += float(np.clip(action[0], -2, 2))
        self.x += 1.0 + 0.1 * self.np_random.standard_normal()
        self.t += 1
        ok = abs(self.robot - self.x) < 3.0
        obs = np.array([self.robot, self.x])
        return obs, float(ok), False, self.t >= self.horizon, {"success": ok}


class Follow:
    def reset(self, *, seed=None):
        return None

    def act(self, obs):
        return np.array([obs[1] - obs[0] + 1.0])


def _robots(channel, q=1.0):
    envs = [
        LinkObservationWrapper(Drift(), channel.links[i], StaticQos(q, 1)) for i in range(channel.n)
    ]
    return envs, [PassThroughEstimator() for _ in envs], [Follow() for _ in envs]


def test_wifi_link_is_a_link():
    assert isinstance(WifiLink.single(CELL, seed=0), Link)


def test_single_robot_gets_every_state_one_step_late():
    link = WifiLink.single(CELL, seed=0)
    link.reset(seed=1, prior=[0.0])
    ages = []
    for t in range(8):
        rx = link.step([float(t)], QosRequest(1.0, 1))
        ages.append(rx.age)
        if t >= 1 and rx.age == 1:
            assert rx.observation.tolist() == [float(t - 1)]
    # one robot on MCS 1, 40 MHz: the channel has room; only the link's own loss shows
    assert ages[0] == 1 and np.mean(np.array(ages[1:]) == 1) >= 0.6


def _unloaded(config, q, *, steps, seed=0):
    """One robot alone asking ``q`` (tau = 1) for ``steps`` steps: (delivered, late, q0)."""
    channel = SharedChannel(config, 1, seed=seed)
    link = channel.links[0]
    link.reset(seed=seed, prior=[0.0])
    for _ in range(steps):
        link.step([0.0], QosRequest(q, 1))
    link.close()
    channel._advance_to(channel.capture_tick(0, steps + 1), -1)  # every deadline has passed
    summary = channel.summary()
    assert int(summary["steps"].sum()) == steps
    return int(summary["delivered"].sum()), int(summary["late"].sum())


@pytest.mark.parametrize("q", [0.3, 0.6])
def test_an_unloaded_link_delivers_the_requested_reliability(q):
    """eq_drop with the link's own delivery: the paper cell's links deliver 99.4-100 %, and a
    robot asking for q gets q (with a fixed q0 = 0.9 it got q / 0.9)."""
    steps = 600
    delivered, late = _unloaded(CELL, q, steps=steps, seed=3)
    assert late == 0  # one robot: the channel has room, every admitted frame is in time
    assert binomtest(delivered, steps, q).pvalue > 1e-3


def test_a_lossy_link_delivers_q_up_to_its_own_delivery_then_all_it_can():
    """A fixed MCS 3 link at 24.4 m (no fading): delivery p ~ 0.75 from the PER model
    ([per]); the delivered fraction is q for q <= p and p above (eq_drop never drops then)."""
    d = 24.4
    ch = ChannelConfig(fixed_mcs=3, distances_m=(d,), rician_k_db=math.inf)
    config = WifiConfig(channel=ch, mac=CELL.mac)
    mac, traffic, bw = config.mac, config.traffic, config.phy.bandwidth_mhz
    p = 1.0
    for uplink, frame in ((True, traffic.ul_frame_bytes), (False, traffic.dl_frame_bytes)):
        snr = ch.snr_db(np.array([d]), np.ones(1), bw, uplink=uplink)
        p *= float(frame_delivery_probability(3, snr, mac.psdu_bits(frame) / 8)[0])
    assert 0.6 < p < 0.9
    steps = 400
    for q in (0.3, 0.6, 0.95):
        delivered, late = _unloaded(config, q, steps=steps, seed=5)
        assert late == 0
        assert binomtest(delivered, steps, min(q, p)).pvalue > 1e-3, (q, delivered / steps)


def test_zero_latency_is_rejected():
    link = WifiLink.single(CELL, seed=0)
    link.reset(prior=[0.0])
    with pytest.raises(ValueError, match="latency_steps"):
        link.step([1.0], QosRequest(1.0, 0))


def test_lockstep_violation_raises():
    channel = SharedChannel(CELL, 3, seed=0)
    for link in channel.links:
        link.reset(prior=[0.0])
    channel.links[0].step([0.0], QosRequest(1.0, 1))
    with pytest.raises(RuntimeError, match="lockstep"):
        channel.links[2].step([0.0], QosRequest(1.0, 1))  # station 1 (offset 13) not sent


def test_rollout_shared_is_deterministic_and_reports_stats():
    channel = SharedChannel(CELL, 3)
    tables = rollout_shared(*_robots(channel), channel=channel, seed=7)
    first = [t.copy() for t in tables]
    summary = channel.summary()
    assert len(tables) == 3 and all(len(t) == Drift.horizon for t in tables)
    assert summary["frames"].sum() == 3 * (Drift.horizon + 1)  # reset sends one too
    assert (summary["mean_latency_ms"].dropna() <= 40.0).all()
    channel2 = SharedChannel(CELL, 3)
    again = rollout_shared(*_robots(channel2), channel=channel2, seed=7)
    for a, b in zip(first, again, strict=True):
        assert a.equals(b)
    assert channel2.summary().equals(summary)
    other = rollout_shared(*_robots(channel2), channel=channel2, seed=8)
    assert not all(a.equals(b) for a, b in zip(first, other, strict=True))


def test_overload_makes_frames_late_and_lower_q_helps():
    heavy = SharedChannel(CELL, 12)
    rollout_shared(*_robots(heavy, q=1.0), channel=heavy, seed=0, max_steps=10)
    light = SharedChannel(CELL, 12)
    rollout_shared(*_robots(light, q=0.3), channel=light, seed=0, max_steps=10)
    late_heavy = heavy.summary()["late"].sum()
    assert late_heavy > 0
    assert light.summary()["late"].sum() < late_heavy
    # eq_drop: q = 0.3 over links that deliver 99.4-100 % admits about 30 % of the frames
    admitted = light.summary()["frames"].sum() / light.summary()["steps"].sum()
    assert admitted == pytest.approx(0.3, abs=0.1)


def test_trace_of_a_run_replays_to_the_same_deliveries():
    from codesign_mb.wifi import offline_optimum, replay

    channel = SharedChannel(CELL, 8, scheduler="convex")
    rollout_shared(*_robots(channel), channel=channel, seed=3, max_steps=6)
    trace = channel.trace()
    online = int(channel.summary()["delivered"].sum())
    # the replay stops at the same horizon, so it delivers what the online run delivered
    assert replay(trace, "convex").delivered >= online
    assert offline_optimum(trace).optimum + 1e-6 >= online


def test_trace_json_round_trip(tmp_path):
    from codesign_mb.wifi import Trace, generate_trace

    trace = generate_trace(CELL, 3, steps=2, seed=0)
    trace.save(tmp_path / "t.json")
    back = Trace.load(tmp_path / "t.json")
    assert back.frames.equals(trace.frames)
    np.testing.assert_allclose(back.ul_bpss, trace.ul_bpss)
    assert back.config == trace.config
    bad = trace.to_json()
    bad["config"]["phy"]["bandwidth"] = 40
    with pytest.raises(ValueError, match="bandwidth"):
        Trace.from_json(bad)


class UnevenDrift(Drift):
    """:class:`Drift` whose episodes last 20-29 steps (drawn at reset): robots drift apart."""

    def reset(self, *, seed=None, options=None):
        out = super().reset(seed=seed, options=options)
        self.horizon = 20 + int(self.np_random.integers(0, 10))
        return out


def test_continuous_operation_runs_episodes_back_to_back_on_one_channel():
    channel = SharedChannel(CELL, 3)
    envs, estimators, controllers = _robots(channel)
    envs = [
        LinkObservationWrapper(UnevenDrift(), link, StaticQos(1.0, 1)) for link in channel.links
    ]
    tables = rollout_shared(
        envs, estimators, controllers, channel=channel, seed=5, episodes=2, warmup_episodes=1
    )
    summary, frames = channel.summary(), channel.trace().frames
    drawn = []
    for i, table in enumerate(tables):
        # the two counted episodes, each as long as its own drawn horizon
        lengths = table.groupby("episode").size()
        assert list(lengths.index) == [0, 1] and lengths.between(20, 29).all()
        drawn.extend(lengths)
        # one frame per step on the channel's clock, never restarted: steps 0, 1, ... with
        # no gap or repeat across the episodes (q = 1, every frame admitted)
        steps = np.sort(frames.loc[frames["station"] == i, "step"].to_numpy())
        assert np.array_equal(steps, np.arange(len(steps)))
        assert len(steps) == summary["steps"][i] >= 3 * 21
    # every episode its own seed: the horizons drawn differ
    assert len(set(drawn)) > 1
    # a robot done with its episodes keeps working until the last robot is: step counts
    # differ by less than one episode
    assert summary["steps"].max() - summary["steps"].min() <= 29 + 1
    again = SharedChannel(CELL, 3)
    envs2 = [LinkObservationWrapper(UnevenDrift(), link, StaticQos(1.0, 1)) for link in again.links]
    tables2 = rollout_shared(
        envs2, *_robots(again)[1:], channel=again, seed=5, episodes=2, warmup_episodes=1
    )
    for a, b in zip(tables, tables2, strict=True):
        assert a.equals(b)
