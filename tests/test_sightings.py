"""Teammate sightings: the model's likelihood and bearing wrap, its validation, both filters
fusing it (compass and estimated headings), and the MRCLAM reader on files written here."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from relloc.config import RobotConfig, TeamConfig
from relloc.estimators.gaussian_sum.filter import CalibrationLayout, GaussianSumFilter
from relloc.estimators.particle.filter import ParticleFilter
from relloc.events import GroundTruthEvent, OdometryEvent, SightingEvent
from relloc.filter.measurement import ModelContext
from relloc.filter.registry import model_for
from relloc.filter.sightings import SightingBatch, wrap
from relloc.filter.state import StateLayout
from relloc.sources.mrclam import MrclamSource, integrate_odometry, is_mrclam


def _config(n: int = 2) -> TeamConfig:
    return TeamConfig(
        tuple(RobotConfig(f"r{i}") for i in range(n)), "r0", area=(-5.0, 5.0, -5.0, 5.0)
    )


class _Validation:
    def __init__(self, config: TeamConfig) -> None:
        self.config = config
        self.layout = StateLayout(config.robot_names, config.reference)

    def is_late(self, t: float) -> bool:
        return t < 0.0

    def memory(self, model: type) -> dict:
        return {}


def test_the_registry_gives_sightings_their_model() -> None:
    assert model_for(SightingEvent(0.0, "r0", "r1", 1.0, 0.0)) is SightingBatch


@pytest.mark.parametrize(
    ("event", "reason"),
    [
        (SightingEvent(0.0, "r0", "r9", 1.0, 0.0), "unknown_robot"),
        (SightingEvent(0.0, "r0", "r0", 1.0, 0.0), "self_observation"),
        (SightingEvent(0.0, "r0", "r1", math.nan, 0.0), "invalid_sighting"),
        (SightingEvent(0.0, "r0", "r1", 1.0, math.inf), "invalid_sighting"),
        (SightingEvent(0.0, "r0", "r1", None, None), "invalid_sighting"),
        (SightingEvent(0.0, "r0", "r1", -1.0, 0.0), "invalid_sighting"),
        (SightingEvent(0.0, "r0", "r1", 1.0, 0.0, sigma_range=0.0), "invalid_sighting"),
        (SightingEvent(0.0, "r0", "r1", 1.0, 3.5), "bearing_out_of_range"),
        (SightingEvent(-1.0, "r0", "r1", 1.0, 0.0), "late_measurement"),
        (SightingEvent(0.0, "r0", "r1", None, -math.pi), None),
        (SightingEvent(0.0, "r0", "r1", 2.0, None), None),
    ],
)
def test_bad_sightings_are_named(event: SightingEvent, reason: str | None) -> None:
    assert SightingBatch.rejection(event, _Validation(_config())) == reason


def test_the_bearing_residual_wraps_at_pi() -> None:
    """r1 straight behind the reference (heading 0): a bearing of +179 deg and one of -179 deg
    are both 1 deg off; the likelihood does not see 358 deg."""
    config = _config()
    layout = StateLayout(config.robot_names, config.reference)
    x = np.array([[-2.0, 0.0]])
    context = ModelContext(config, layout, robust=False, yaws={"r0": 0.0, "r1": 0.0})
    lls = []
    for b in (math.radians(179.0), math.radians(-179.0)):
        (model,) = SightingBatch.build(
            [SightingEvent(0.0, "r0", "r1", None, b, 0.1, math.radians(1.0))], context
        )
        lls.append(float(model.log_likelihood(layout.positions(x), x)[0]))
    expected = -0.5 - math.log(math.radians(1.0)) - 0.5 * math.log(2 * math.pi)
    assert lls == pytest.approx([expected, expected], abs=1e-9)
    assert wrap(math.radians(358.0)) == pytest.approx(math.radians(-2.0))


def test_a_range_and_bearing_sighting_fixes_a_position_in_the_particle_filter() -> None:
    """The reference (heading 90 deg in the shared frame) sees r1 at 2 m, 30 deg left: r1 is
    at 2 (cos 120, sin 120)."""
    config = _config()
    layout = StateLayout(config.robot_names, config.reference)
    pf = ParticleFilter(layout, 40_000, config.area, rng=np.random.default_rng(0))
    context = ModelContext(config, layout, robust=False, yaws={"r0": math.pi / 2, "r1": 0.0})
    sighting = SightingEvent(0.0, "r0", "r1", 2.0, math.radians(30.0), 0.2, math.radians(5.0))
    before = pf.estimate().mean[0]
    assert pf.update(SightingBatch.build([sighting], context))
    est = pf.estimate().mean[0]
    truth = [2 * math.cos(math.radians(120)), 2 * math.sin(math.radians(120))]
    assert np.hypot(*(before - truth)) > 1.0
    assert est == pytest.approx(truth, abs=0.1)


def test_without_a_heading_the_particle_filter_gets_the_range_only() -> None:
    config = _config()
    layout = StateLayout(config.robot_names, config.reference)
    context = ModelContext(config, layout, yaws={"r0": 0.0, "r1": 0.0}, shared_heading=False)
    (model,) = SightingBatch.build([SightingEvent(0.0, "r0", "r1", 2.0, 0.3)], context)
    assert isinstance(model, SightingBatch)
    assert [row.kind for row in model.items] == ["range"]


def test_a_sighting_turns_an_unknown_heading_in_the_gaussian_sum_filter() -> None:
    """Headings estimated: r1 (its odometry frame turned by 70 deg from the reference's, odometry
    yaw 0) sees the reference at 3 m. Each Gaussian starts at the true position with its
    heading unknown (u ~ N(0, I/2)); the sightings turn u to 70 deg."""
    config = _config()
    layout = CalibrationLayout(config.robot_names, config.reference, heading=True)
    gsf = GaussianSumFilter(
        layout, 20, config.area, rng=np.random.default_rng(0), position_sigma=0.05
    )
    theta = math.radians(70.0)
    p1 = np.array([1.0, 2.0])
    gsf.initialize(np.tile(p1, (20, 1)))
    # the reference as r1 sees it: -p1 turned into r1's body frame (r1's heading is theta)
    c, s = math.cos(theta), math.sin(theta)
    body = np.array([c * -p1[0] + s * -p1[1], -s * -p1[0] + c * -p1[1]])
    sighting = SightingEvent(
        0.0, "r1", "r0", float(np.hypot(*body)), math.atan2(body[1], body[0]), 0.05, 0.01
    )
    context = ModelContext(config, layout, yaws={"r0": 0.0, "r1": 0.0}, shared_heading=False)
    for _ in range(5):
        assert gsf.update(SightingBatch.build([sighting], context))
    mean, spread = gsf.heading("r1")
    assert math.degrees(mean) == pytest.approx(70.0, abs=2.0)
    assert math.degrees(spread) < 5.0


def test_a_sighting_does_not_read_the_observers_odometry_scale_into_the_range() -> None:
    """Headings and scales estimated: r1 drives squares (0.1 m steps, a right angle every 20)
    with an odometry that says 10 % more than it drives, its frame turned by 40 deg, and sees
    the static reference at every step. Its scale comes out at 0.9, its position within 0.1 m.
    (Read as ``(A(w) u) . v = r``, the range would be the scale times the distance: 0.949 and a
    0.14 m error.)"""
    config = _config()
    layout = CalibrationLayout(config.robot_names, config.reference, heading=True, scale=True)
    gsf = GaussianSumFilter(
        layout, 20, config.area, rng=np.random.default_rng(0), position_sigma=0.3
    )
    theta, scale = math.radians(40.0), 0.9
    c, s = math.cos(theta), math.sin(theta)
    p1 = np.array([2.0, 1.0])
    gsf.initialize(p1 + np.random.default_rng(1).normal(0.0, 0.3, (20, 2)))
    rng = np.random.default_rng(2)
    psi = 0.0
    for k in range(300):
        turn = math.pi / 2 if k % 20 == 19 else 0.0
        odo = 0.1 * np.array(
            [math.cos(psi + 0.5 * turn), math.sin(psi + 0.5 * turn)]
        )  # in r1's odometry frame
        p1 = p1 + scale * np.array([c * odo[0] - s * odo[1], s * odo[0] + c * odo[1]])
        psi += turn
        gsf.predict(np.array([[0.0, 0.0], odo]), np.array([0.0, 0.002]), 0.5)
        bearing = math.remainder(
            math.atan2(-p1[1], -p1[0]) - (theta + psi) + rng.normal(0.0, 0.005), math.tau
        )
        sighting = SightingEvent(
            0.5 * k, "r1", "r0", float(np.hypot(*p1)) + rng.normal(0.0, 0.03), bearing, 0.03, 0.005
        )
        context = ModelContext(config, layout, yaws={"r0": 0.0, "r1": psi}, shared_heading=False)
        assert gsf.update(SightingBatch.build([sighting], context))
        gsf.maybe_resample()
    assert gsf.scale("r1")[0] == pytest.approx(0.9, abs=0.02)
    assert math.degrees(gsf.heading("r1")[0]) == pytest.approx(40.0, abs=2.0)
    assert float(np.hypot(*(gsf.estimate().mean[0] - p1))) < 0.1


def test_a_wide_heading_is_split_in_three_that_keep_the_mixtures_moments() -> None:
    """r1 drove 2 m on a heading known to 0.3 rad: its position co-varies with its ``u``.
    Splitting (threshold 0.2 rad) replaces every Gaussian by three along the heading's tangent,
    resampled back to the same count; the mixture keeps its mean and covariance, each Gaussian's
    angular variance shrinks to 0.45 of it, and nothing is split again at 0.25 rad."""
    config = _config()
    layout = CalibrationLayout(config.robot_names, config.reference, heading=True)
    m = 4000
    gsf = GaussianSumFilter(layout, m, config.area, rng=np.random.default_rng(0))
    c0, c1 = layout.u_columns("r1")
    mean = np.zeros(layout.width)
    mean[:2], mean[c0], mean[layout.u_columns("r0")[0]] = (2.0, 1.0), 1.0, 1.0
    p_uu = np.diag([0.1**2, 0.3**2])
    cov = np.eye(layout.width) * 1e-6
    cov[:2, :2] = 4.0 * p_uu + 0.01 * np.eye(2)
    cov[:2, c0 : c1 + 1] = cov[c0 : c1 + 1, :2] = 2.0 * p_uu  # positions = 2 u + noise
    cov[c0 : c1 + 1, c0 : c1 + 1] = p_uu
    gsf.mean[:], gsf.cov = np.tile(mean, (m, 1)), np.tile(cov, (m, 1, 1))
    assert gsf.split_headings(0.2) == m
    assert gsf.n == m and np.allclose(gsf.weights(), 1.0 / m)
    mixture_mean = gsf.mean.mean(axis=0)
    centred = gsf.mean - mixture_mean
    mixture_cov = gsf.cov.mean(axis=0) + centred.T @ centred / m
    assert mixture_mean == pytest.approx(mean, abs=0.02)
    assert mixture_cov[:4, :4] == pytest.approx(cov[:4, :4], abs=0.02)
    assert gsf.cov[:, c1, c1] == pytest.approx(0.09 * 0.6715662887**2, rel=1e-6)
    assert gsf.split_headings(0.25) == 0


# ---------------------------------------------------------------------------- MRCLAM reader
_HEADER = "# UTIAS Multi-Robot Cooperative Localization and Mapping Dataset\n# a test file\n"


def _write_dataset(folder: Path) -> None:
    folder.mkdir()
    (folder / "Barcodes.dat").write_text(_HEADER + "  1 \t 5\n  2 \t 14\n  3 \t 41\n  6 \t 90\n")
    # robot1 drives straight at 0.1 m/s for 2 s, then turns in place at 0.5 rad/s for 1 s
    (folder / "Robot1_Odometry.dat").write_text(
        _HEADER
        + "100.0 \t 0.1 \t 0.0\n101.0 \t 0.1 \t 0.0\n102.0 \t 0.0 \t 0.5\n103.0 \t 0.0 \t 0.0\n"
    )
    (folder / "Robot2_Odometry.dat").write_text(
        _HEADER + "100.5 \t 0.0 \t 0.0\n102.5 \t 0.0 \t 0.0\n"
    )
    # robot1 sees robot2 (barcode 14), a landmark (90) and an unknown barcode (77)
    (folder / "Robot1_Measurement.dat").write_text(
        _HEADER
        + "100.2 \t 14 \t 2.0 \t 0.1\n100.4 \t 90 \t 3.0 \t -0.2\n101.1 \t 77 \t 1.0 \t 0.0\n"
    )
    (folder / "Robot2_Measurement.dat").write_text(_HEADER + "101.5 \t 5 \t 1.9 \t 3.0\n")
    for i in (1, 2):
        (folder / f"Robot{i}_Groundtruth.dat").write_text(
            _HEADER + f"100.0 \t {i}.0 \t 0.5 \t 0.1\n103.0 \t {i}.5 \t 0.5 \t 0.2\n"
        )


def test_the_mrclam_reader_turns_a_data_set_into_events(tmp_path: Path) -> None:
    folder = tmp_path / "MRCLAM_Test"
    _write_dataset(folder)
    assert is_mrclam(folder) and not is_mrclam(tmp_path)
    config = TeamConfig((RobotConfig("robot1"), RobotConfig("robot2")), "robot1")
    source = MrclamSource(folder, config)
    assert source.duration == pytest.approx(3.0)
    events = list(source)
    assert [e.t for e in events] == sorted(e.t for e in events)
    odo = [e for e in events if isinstance(e, OdometryEvent) and e.robot == "robot1"]
    # stamped ODOMETRY_DELAY after the velocity command, when the robot follows it
    assert [e.t for e in odo] == pytest.approx([100.24, 101.24, 102.24, 103.24])
    assert [(round(e.x, 9), round(e.y, 9), round(e.yaw, 9)) for e in odo] == [
        (0.0, 0.0, 0.0),
        (0.1, 0.0, 0.0),
        (0.2, 0.0, 0.0),
        (0.2, 0.0, 0.5),
    ]
    sightings = [e for e in events if isinstance(e, SightingEvent)]
    assert [(s.observer, s.target, s.range, s.bearing) for s in sightings] == [
        ("robot1", "robot2", 2.0, 0.1),
        ("robot2", "robot1", 1.9, 3.0),
    ]
    assert sightings[0].sigma_range == pytest.approx(0.06 + 0.02 * 2.0)
    assert source.stats.counts["landmark_sightings"] == 1
    assert source.stats.rejected == {"unknown_barcode": 1}
    truth = [e for e in events if isinstance(e, GroundTruthEvent)]
    assert len(truth) == 4 and truth[0].position[0] == 1.0


def test_odometry_integration_follows_arcs() -> None:
    """A quarter circle of radius 1 m (v pi/2 m/s, w pi/2 rad/s for 1 s) ends at (1, 1)."""
    poses = integrate_odometry(np.array([[0.0, math.pi / 2, math.pi / 2], [1.0, 0.0, 0.0]]))
    assert poses[-1] == pytest.approx([1.0, 1.0, math.pi / 2])


def test_the_first_300_s_of_mrclam_dataset_6_from_the_uniform_prior(shared_data: Path) -> None:
    """The shipped config (headings and scales estimated) on the real data, cut to 300 s and
    200 Gaussians after a 5 000-particle start, without the heading split, seed 0: every
    robot's body-frame median within 0.24 m and their mean within 0.18 m (measured
    0.125-0.229 m, mean 0.172; seeds 1-2 alike; before the scales were held to their interval
    and heading corrections turned them 0.126-0.198, mean 0.171: robot1 lost what robot4
    gained), and the odometry scales below 1 on average (measured 0.951; Vicon says 0.94, the
    Creates drive 4-9 % less than their commands; before 0.984; reading a sighting's range as
    scale times distance gave 1.023; with the split's resampling 1.011, so this check of the
    rows runs without it). Figures of the whole run: docs/explanation/mrclam.md."""
    import itertools

    from relloc.engine import Engine
    from relloc.evaluation.metrics import GroundTruth
    from relloc.evaluation.report import evaluate
    from relloc.methods import build_pipeline

    folder = shared_data / "mrclam" / "MRCLAM_Dataset6"
    if not is_mrclam(folder):
        pytest.skip(f"MRCLAM Dataset 6 not found: {folder}")
    config = TeamConfig.load(
        Path(__file__).resolve().parents[1] / "configs" / "mrclam" / "dataset6.toml"
    )
    config = config.with_filter(
        selfcal_particles=200, selfcal_init_particles=5000, heading_split_std=0.0
    )
    source = MrclamSource(folder, config)
    truth = GroundTruth(config.reference)
    pipeline = build_pipeline("pf", config, seed=0)
    events = itertools.takewhile(lambda e: e.t < source.start_time + 300.0, source)
    report = evaluate(
        Engine([pipeline], truth_sinks=[truth.add]).run(events), truth, "dataset6", 30.0
    )
    body = report.methods["pf"].body_frame
    assert set(body) == {"robot1", "robot3", "robot4", "robot5"}
    assert all(s.n > 900 and s.median < 0.24 for s in body.values()), {
        r: (s.n, s.median) for r, s in body.items()
    }
    assert float(np.mean([s.median for s in body.values()])) < 0.18
    scales = [v[0] for v in pipeline.estimates[-1].scales.values()]
    assert float(np.mean(scales)) < 1.0


# ---------------------------------------------------------------------------- simulator, EKF
def test_simulated_aoa_sightings_leave_the_other_draws_alone() -> None:
    """UWB angle of arrival beside the ranges: bearings in the observer's body frame within
    its field of view, 5 deg noise; the scenario's ranges and odometry are drawn as before."""
    from relloc.events import RangeEvent
    from relloc.odometry import wrap_angle
    from relloc.simulator import multi_scenario
    from relloc.simulator.error_models import UWB_AOA

    plain = [
        e for e in multi_scenario(0, duration=10.0).events() if not isinstance(e, SightingEvent)
    ]
    sim = multi_scenario(0, duration=10.0, sightings=(UWB_AOA,))
    events = list(sim.events())
    assert [e for e in events if not isinstance(e, SightingEvent)] == plain
    sightings = [e for e in events if isinstance(e, SightingEvent)]
    assert len(sightings) > 500 and all(
        e.range is None and e.sensor == "uwb_aoa" for e in sightings
    )
    assert any(isinstance(e, RangeEvent) for e in events)
    errors = []
    for e in sightings:
        xo, yo, yaw = sim.true_pose(e.observer, e.t)
        xt, yt, _ = sim.true_pose(e.target, e.t)
        errors.append(float(wrap_angle(e.bearing - (math.atan2(yt - yo, xt - xo) - yaw))))
    errors_deg = np.degrees(np.abs(errors))
    assert np.all(
        np.abs([e.bearing for e in sightings]) <= math.radians(60.0 + 4 * 5.0)
    )  # field of view + noise
    assert np.median(errors_deg) == pytest.approx(5.0 * 0.674, rel=0.15)  # median |N(0, 5 deg)|


def test_the_oracle_ekf_tracks_a_team_from_camera_sightings() -> None:
    """Three simulated robots with teammate cameras; the EKF starts at their true poses."""
    from relloc.evaluation.gauges import body_frame_paired
    from relloc.evaluation.metrics import GroundTruth, associate
    from relloc.localizers.ekf import EkfOracleLocalizer
    from relloc.simulator import multi_scenario
    from relloc.simulator.error_models import TEAMMATE_CAMERA

    sim = multi_scenario(1, duration=30.0, sightings=(TEAMMATE_CAMERA,))
    start = {r: sim.true_pose(r, 0.0) for r in sim.robots}
    loc = EkfOracleLocalizer(sim.config, start)
    gt = GroundTruth(sim.config.reference)
    estimates = []
    for ev in sim.events():
        if isinstance(ev, GroundTruthEvent):
            gt.add(ev)
        estimates += loc.process(ev)
    estimates += loc.flush()
    assert loc.stats["sighting"] > 200
    paired = associate(estimates, gt, loc.layout.others)
    body = body_frame_paired(
        estimates, gt, loc.layout.others, loc.odometry_yaws[sim.config.reference]
    )
    for robot in loc.layout.others:
        assert np.median(paired[robot].errors) < 0.15
        assert np.median(body[robot].errors) < 0.15


def test_the_self_calibrating_filter_tracks_drifting_headings_with_sightings() -> None:
    """Gyro biases of up to 0.6 deg/s turn the odometry frames by up to 50 deg in 90 s; with
    headings estimated (from the uniform prior) and teammate cameras beside the ranges, the
    positions in the reference's body frame stay within 0.15 m over the last 45 s."""
    from relloc.engine import Engine
    from relloc.evaluation.metrics import GroundTruth
    from relloc.evaluation.report import evaluate
    from relloc.methods import build_pipeline
    from relloc.simulator import multi_scenario
    from relloc.simulator.error_models import TEAMMATE_CAMERA, OdometryErrorModel

    sim = multi_scenario(
        0,
        duration=90.0,
        odometry=OdometryErrorModel(gyro_bias_max=0.01),
        sightings=(TEAMMATE_CAMERA,),
    )
    assert max(abs(b) for b in sim.true_gyro_biases.values()) * 90.0 > math.radians(45.0)
    config = sim.config.with_modes(heading="estimate").with_filter(
        selfcal_particles=200, selfcal_init_particles=5000
    )
    truth = GroundTruth(config.reference)
    pipeline = build_pipeline("pf", config, seed=0)
    engine = Engine([pipeline], truth_sinks=[truth.add]).run(sim.events())
    report = evaluate(engine, truth, "drift", 45.0)
    body = report.methods["pf"].body_frame
    assert set(body) == set(config.robot_names) - {config.reference}
    assert all(s.n > 300 and s.median < 0.15 for s in body.values())
    assert pipeline.localizer.stats["sighting"] > 1000


# ---------------------------------------------------------------------------- ROS 2
def test_sightings_arrive_as_point_stamped_in_the_observers_body_frame() -> None:
    """``geometry_msgs/PointStamped`` of a teammate in the observer's base_link, one topic per
    ordered pair from the observer's ``sighting_topic`` template, through the shared ingestion
    layer (the rosbag and Zenoh sources) to a range-and-bearing sighting."""
    from relloc.ros.messages import POINT_STAMPED, encode, sighting_msg
    from relloc.sources.clock import HeaderClock
    from relloc.sources.ingest import Converter, IngestStats, team_routes

    config = TeamConfig(
        (
            RobotConfig(
                "tb1", sighting_topic="/tb1/teammates/{target}", sighting_sigma_bearing_deg=2.0
            ),
            RobotConfig("tb2"),
            RobotConfig("tb3"),
        ),
        "tb1",
    )
    routes = [r for r in team_routes(config) if r.kind == "sighting"]
    assert [(r.topic, r.robot, r.robot_b, r.msgtypes) for r in routes] == [
        ("/tb1/teammates/tb2", "tb1", "tb2", (POINT_STAMPED,)),
        ("/tb1/teammates/tb3", "tb1", "tb3", (POINT_STAMPED,)),
    ]
    sent = SightingEvent(12.5, "tb1", "tb3", 2.5, -2.8, 0.1, math.radians(2.0))
    payload = encode(sighting_msg(sent, frame_id="tb1/base_link"), POINT_STAMPED)
    got = Converter(IngestStats(), HeaderClock()).convert(routes[1], routes[1].topic, payload, 12.6)
    assert isinstance(got, SightingEvent)
    assert (got.t, got.observer, got.target, got.sensor) == (12.5, "tb1", "tb3", "ros")
    assert got.range == pytest.approx(2.5) and got.bearing == pytest.approx(-2.8)
    assert (got.sigma_range, got.sigma_bearing) == pytest.approx((0.1, math.radians(2.0)))
