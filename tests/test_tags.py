"""Several UWB tags per robot: the config's tags and lever arms, the range routes between every
two robots' tags, the node pairs of the online biases, the smoother's and multilateration's
points (a robot's tags, fitted to its lever arms) and the score of a published heading."""

from __future__ import annotations

import math
from dataclasses import replace
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from relloc import geometry
from relloc.config import ConfigError, RobotConfig, TagConfig, TeamConfig
from relloc.engine import Engine, Pipeline
from relloc.estimate import BODY_FRAME, Estimate
from relloc.evaluation.metric import MethodRun
from relloc.evaluation.metrics import GroundTruth
from relloc.evaluation.report import evaluate
from relloc.evaluation.yaw_scores import YawError, YawResult
from relloc.events import GroundTruthEvent, OdometryEvent, RangeEvent
from relloc.filter.state import StateLayout
from relloc.filter.tag_points import TagPoints
from relloc.localizers.priors import bias_layout
from relloc.methods import build_pipeline
from relloc.sensors.builtin import Range
from relloc.simulator.scenarios import tags_odometry_scenario, tags_scenario

FloatArray = NDArray[np.float64]

TEAM = """
reference = "a"
[[robots]]
name = "a"
tags = [{ node = "n_1", lever_arm = [0.15, 0.0] }, { node = "n_2", lever_arm = [-0.15, 0.0] }]
[[robots]]
name = "b"
uwb_node = "n_3"
[[robots]]
name = "c"
uwb_node = "n_4"
"""


def _team(tmp_path: Path, text: str = TEAM) -> TeamConfig:
    path = tmp_path / "team.toml"
    path.write_text(text)
    return TeamConfig.load(path)


def test_a_robot_lists_its_tags_with_lever_arms_and_one_uwb_node_stays_one_tag(
    tmp_path: Path,
) -> None:
    config = _team(tmp_path)
    a, b = config.robot("a"), config.robot("b")
    assert a.nodes == ("n_1", "n_2") and b.nodes == ("n_3",)
    assert config.lever_arm("n_2") == (-0.15, 0.0) and config.lever_arm("n_3") == (0.0, 0.0)
    assert config.robot_of_node("n_2") == "a" and config.robot_of_node("n_9") is None
    assert config.multi_tag_robots == ("a",) and config.has_lever_arms
    assert TeamConfig.from_dict(config.to_dict()) == config
    assert _team(tmp_path, config.to_toml()) == config


@pytest.mark.parametrize(
    ("robot", "message"),
    [
        ('uwb_node = "n_1"\ntags = [{ node = "n_5" }]', "not both"),
        ('tags = [{ node = "n_5" }, { node = "n_5" }]', "listed twice"),
        ('tags = [{ node = "n_5", lever_arm = [0.1] }]', "lever_arm"),
        ('tags = [{ node = "n_3" }]', "one robot only"),
        ("tags = [{ lever_arm = [0.1, 0.0] }]", "node"),
    ],
)
def test_bad_tags_are_config_errors(tmp_path: Path, robot: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        _team(tmp_path, TEAM + f'[[robots]]\nname = "d"\n{robot}\n')


def test_ranges_are_read_between_every_two_robots_tags_never_within_one(tmp_path: Path) -> None:
    config = _team(tmp_path)
    topics = {r.topic for r in Range().team_routes(config)}
    pairs = {("n_1", "n_3"), ("n_2", "n_3"), ("n_1", "n_4"), ("n_2", "n_4"), ("n_3", "n_4")}
    expected = {f"/uwb/tof/{x}/{y}/distance" for p in pairs for x, y in (p, p[::-1])}
    assert topics == expected


def test_each_tag_pair_between_robots_has_its_own_online_bias(tmp_path: Path) -> None:
    config = _team(tmp_path).with_modes(bias="online")
    layout, prior = bias_layout(config)
    assert layout.bias_pairs == ("n_1-n_3", "n_1-n_4", "n_2-n_3", "n_2-n_4", "n_3-n_4")
    assert prior.latents == ("team", "n_1", "n_2", "n_3", "n_4")


def _two_tag_team(
    seed: int, tags: bool, n: int = 5, arm: float = 0.15
) -> tuple[TeamConfig, list[RangeEvent], FloatArray]:
    """``n`` robots standing still at seeded positions and headings, each with two tags
    ``arm`` either side of its centre on its x axis (or, without ``tags``, one at its centre),
    every two robots' tags ranging at 10 Hz for 30 s (noise 0.05 m, no bias); no odometry."""
    rng = np.random.default_rng(seed)
    pos = rng.uniform(0.0, 6.0, (n, 2))
    yaw = rng.uniform(-math.pi, math.pi, n)
    robots: list[dict[str, Any]] = []
    for i in range(n):
        if tags:
            arms = [{"node": f"n_{i}a", "lever_arm": [arm, 0.0]}]
            arms.append({"node": f"n_{i}b", "lever_arm": [-arm, 0.0]})
            robots.append({"name": f"r{i}", "tags": arms})
        else:
            robots.append({"name": f"r{i}", "uwb_node": f"n_{i}a"})
    config = TeamConfig.from_dict(
        {
            "reference": "r0",
            "area": [-2.0, 8.0, -2.0, 8.0],
            "robots": robots,
            "uwb": {"default_bias": 0.0, "default_bias_sigma": 0.05},
            "filter": {"kind": "smoother"},
        }
    )
    where = {}
    for r in config.robots:
        i = int(r.name[1:])
        for tag in r.tag_list:
            where[tag.node] = (i, geometry.tag_position(pos[i], yaw[i], tag.lever_arm))
    events = []
    nodes = sorted(where)
    for k in range(300):
        for a, b in combinations(nodes, 2):
            (ia, pa), (ib, pb) = where[a], where[b]
            if ia != ib:
                d = float(np.hypot(*(pa - pb))) + rng.normal(0.0, 0.05)
                events.append(RangeEvent(0.1 * k, f"r{ia}", f"r{ib}", d, a, b))
    return config, events, pos


def _shape_error(shape: dict[str, tuple[float, ...]], pos: FloatArray) -> float:
    """Mean distance of a published shape from the truth after the best rotation (either
    reflection), relative to ``r0``."""
    names = sorted(shape)
    est = np.array([shape[r][:2] for r in names])
    truth = np.array([pos[int(r[1:])] - pos[0] for r in names])
    best = math.inf
    for mirror in (1.0, -1.0):
        q = est * np.array([1.0, mirror])
        u, _, vt = np.linalg.svd(q.T @ truth)
        rot = (u @ vt).T
        if np.linalg.det(rot) > 0:
            best = min(best, float(np.mean(np.linalg.norm(q @ rot.T - truth, axis=1))))
    return best


def _ran(method: str, seed: int, tags: bool) -> tuple[Pipeline, FloatArray]:
    """``method`` over :func:`_two_tag_team`, and the true positions."""
    config, events, pos = _two_tag_team(seed, tags)
    pipeline = build_pipeline(method, config)
    Engine([pipeline]).run(iter(events))
    return pipeline, pos


def test_the_smoother_fits_each_robot_to_its_tags_and_never_claims_the_mirror_image() -> None:
    for seed in range(3):
        errors = {}
        for tags in (True, False):
            pipeline, pos = _ran("pf", seed, tags)
            est = pipeline.estimates[-1]
            # ranges are the same for the formation and its mirror image: two tags per robot
            # turn it, not flip it, so nothing here may claim the orientation (or a heading)
            assert not est.orientation_observable and est.yaws == {}
            assert pipeline.localizer.stats["smoother_restarts"] == 0
            errors[tags] = _shape_error(est.shape, pos)
        # measured: 0.019 / 0.014 / 0.017 m with two tags a robot, 0.034 / 0.023 / 0.026 m
        # with one at each centre: four times the ranges, the robots' centres fitted to them
        assert errors[True] < 0.025 and errors[True] < errors[False]


def test_multilateration_solves_for_the_tags_and_fits_each_robot_to_them() -> None:
    for seed in range(3):
        errors = {}
        for tags in (True, False):
            pipeline, pos = _ran("multilateration", seed, tags)
            errors[tags] = np.median([_shape_error(e.positions, pos) for e in pipeline.estimates])
        # measured: 0.028 / 0.025 / 0.027 m with two tags a robot, 0.058 / 0.047 / 0.052 m with
        # one at each centre (the median over the run's estimates)
        assert errors[True] < 0.035 and errors[True] < errors[False]


def test_a_robots_pose_is_the_rigid_fit_of_its_lever_arms_to_its_tags(tmp_path: Path) -> None:
    config = _team(tmp_path)
    points = TagPoints.of(config, StateLayout(config.robot_names, config.reference))
    assert points.size == 4 and points.robot.tolist() == [0, 0, 1, 2] and points.oriented
    yaw, centre = 0.7, np.array([2.0, -1.0])
    tags = [geometry.tag_position(centre, yaw, config.lever_arm(n)) for n in ("n_1", "n_2")]
    world = np.array([*tags, [5.0, 1.0], [2.0, 3.0]])
    pos, yaws = points.poses(world)
    assert np.allclose(pos[0], centre) and yaws[0] == pytest.approx(yaw)
    assert np.isnan(yaws[1:]).all()
    published = points.published(world)  # in r0's body frame: b straight ahead is +x
    ahead = geometry.tag_position(centre, yaw, (3.0, 0.0))
    world[2] = ahead
    assert np.allclose(points.published(world)[:2], [3.0, 0.0])
    assert published.size == 4  # two robots' positions, no multi-tag one among them


def test_a_published_yaw_is_scored_against_the_motion_capture_in_its_frame() -> None:
    truth = GroundTruth("r0")
    for k in range(21):
        t = 0.1 * k
        truth.add(GroundTruthEvent(t, "r0", (0.0, 0.0), 0.5))
        truth.add(GroundTruthEvent(t, "r1", (1.0, 0.0), 0.5 + 0.3))
    # r1's heading in r0's body frame is 0.3 rad; the estimates say 0.3 + 2 deg, then 0.3 - 4
    yaws = [math.radians(2.0)] * 14 + [math.radians(-4.0)] * 7
    estimates = [
        Estimate(
            0.1 * k, "pf", "r0", {"r1": (1.0, 0.0)}, frame=BODY_FRAME, yaws={"r1": (0.3 + e, 0.05)}
        )
        for k, e in enumerate(yaws)
    ]
    run = MethodRun("pf", estimates, truth, ["r1"], 0.0, 0.5, {})
    result = YawError().compute(run)
    assert len(result.errors_deg["r1"]) == 16  # after the warm-up
    # 16 after the warm-up: 9 at 2 deg, 7 at 4 deg
    mean = (9 * 2.0 + 7 * 4.0) / 16
    assert result.robot_json() == {
        "r1": {"yaw_error_median_deg": 2.0, "yaw_error_mean_deg": pytest.approx(mean)}
    }
    assert result.cells("r1") == {"yaw err. (deg)": "2.0"}


def test_the_tags_scenario_ranges_between_tags_at_their_lever_arms() -> None:
    sim = tags_scenario(0, duration=5.0)
    config = sim.config
    assert config.multi_tag_robots == ("r0", "r1", "r2", "r3", "r4")
    assert config.lever_arm("n_2a") == (0.15, 0.0) and config.lever_arm("n_2b") == (-0.15, 0.0)
    assert not any(r.odom_topic for r in config.robots)
    events = list(sim.events())
    assert not any(isinstance(e, OdometryEvent) for e in events)
    ranges = [e for e in events if isinstance(e, RangeEvent)]
    assert len({e.node_pair for e in ranges}) == 40  # 10 robot pairs, 4 tag pairs each
    truth = {e.robot: e for e in events if isinstance(e, GroundTruthEvent) and e.t == 0.0}
    first: dict[str, RangeEvent] = {}
    for e in ranges:
        first.setdefault(e.node_pair, e)

    def tag(robot: str, node: str) -> FloatArray:
        g = truth[robot]
        return geometry.tag_position(g.position, g.yaw, config.lever_arm(node))

    off_tags, off_centres = [], []
    for e in first.values():
        excess = e.distance - sim.true_biases[e.node_pair]
        off_tags.append(
            excess - float(np.hypot(*(tag(e.robot_a, e.node_a) - tag(e.robot_b, e.node_b))))
        )
        centres = np.subtract(truth[e.robot_a].position, truth[e.robot_b].position)
        off_centres.append(excess - float(np.hypot(*centres)))
    # what is left is the range noise and the antenna pattern (up to about 0.2 m), not the arms
    assert np.median(np.abs(off_tags)) < 0.7 * np.median(np.abs(off_centres))


def test_with_odometry_the_smoother_publishes_the_tags_headings_in_the_references_frame() -> None:
    sim = tags_odometry_scenario(0, duration=30.0)
    config = sim.config.with_filter(kind="smoother")
    pipeline = build_pipeline("pf", config)
    truth = GroundTruth(config.reference)
    engine = Engine([pipeline], truth_sinks=[truth.add])
    engine.run(sim.events())
    report = evaluate(engine, truth, "tags", 10.0).methods["pf"]
    est = pipeline.estimates[-1]
    assert est.orientation_observable and est.frame == BODY_FRAME
    assert set(est.yaws) == {"r1", "r2", "r3", "r4"}
    yaw = report.result(YawResult)
    assert yaw is not None
    medians = [yaw.median(r) for r in ("r1", "r2", "r3", "r4")]
    # measured: 4.4 / 4.7 / 2.5 / 10.5 deg; without the simulator's antenna pattern (its
    # heading-dependent range error on a 0.3 m baseline) 1.3-3.5 (docs/explanation/tags.md)
    assert max(medians) < 15.0


def test_calibration_scores_a_tag_pair_against_the_tags_positions(shared_data: Path) -> None:
    """On the seven-robot team, n_8 at a lever arm on turtlebot5: the motion-capture distance of
    its pairs is to the tag, not to the body (turtlebot5's yaw turns the arm into the world)."""
    from relloc.evaluation.calibration import pair_samples_from_bag

    bag = shared_data / "tiers_uwb_rel" / "case4_test1_static"
    base = TeamConfig.load(Path(__file__).resolve().parents[1] / "configs/tiers_uwb_rel/case4.toml")
    arm = (0.0, 0.3)
    robots = tuple(
        replace(r, uwb_node="", tags=(TagConfig("n_5"), TagConfig("n_8", arm)))
        if r.name == "turtlebot5"
        else r
        for r in base.robots
    )
    config = replace(base, robots=robots)
    span = (0.0, 5.0)
    with_arm = pair_samples_from_bag(bag, config, span=span)
    at_body = pair_samples_from_bag(
        bag, replace(config, robots=tuple(_no_arm(r) for r in robots)), span=span
    )
    assert "n_1-n_8" in with_arm and "n_1-n_5" in with_arm
    # n_5 sits at the body origin: its pairs do not move
    assert np.array_equal(with_arm["n_1-n_5"][2], at_body["n_1-n_5"][2])
    moved = float(np.median(with_arm["n_1-n_8"][2] - at_body["n_1-n_8"][2]))
    assert 0.05 < abs(moved) <= 0.3  # the arm's projection on the pair's direction


def _no_arm(robot: RobotConfig) -> RobotConfig:
    return replace(robot, tags=tuple(replace(t, lever_arm=(0.0, 0.0)) for t in robot.tags))


def test_the_particle_filter_turns_the_lever_arms_with_the_odometry_yaws() -> None:
    def ape(arms: bool) -> float:
        sim = tags_odometry_scenario(2, duration=40.0)
        config = sim.config
        if not arms:
            robots = tuple(_no_arm(r) for r in config.robots)
            config = replace(config, robots=robots)
        pipeline = build_pipeline("pf", config, seed=2)
        truth = GroundTruth(config.reference)
        engine = Engine([pipeline], truth_sinks=[truth.add])
        engine.run(sim.events())
        report = evaluate(engine, truth, "tags", 10.0).methods["pf"]
        return float(np.mean([s.median for s in report.robots.values()]))

    # measured, seeds 0-2: 0.057 / 0.052 / 0.074 m with the arms, 0.076 / 0.062 / 0.232 m with
    # each robot's tags taken at its centre (seed 2 lost r4 at 4 s)
    assert ape(True) < 0.09 and ape(False) > 0.15
