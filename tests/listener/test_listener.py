"""The listener: eq. 1 on hand-computed transforms, EMA per edge, every rejection counted."""

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core.markerdata import MarkerData, Rejection
from atlas_onboard.listener import EdgeUpdate, Listener
from atlas_onboard.node.setup import make_graph
from tests.helpers import assert_pose_close, observe, pose, world_from

MS = 1_000_000


def make(doc, alpha=1.0):
    # The paper's filter (eq. 3): without edge ageing, whose inverse-variance filter is tested apart.
    doc = {"fusion": {"ema_alpha": alpha, "age_sigma_m_per_s": 0}, **doc}
    world = world_from(doc)
    graph = make_graph(world)
    return world, graph, Listener(world, graph)


HAND = {
    "entities": {
        "world": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0.5, 0, 0]}}]},
        "drone": {
            "sensors": [
                {"name": "cam", "id": 1, "pose_of": "optical", "pose": {"pos": [1, 0, 0], "rpy_deg": [0, 0, 90]}}
            ]
        },
    }
}


def test_eq1_on_hand_computed_transforms():
    # T1 = drone->camera: rotation 90 deg about z, translation (1, 0, 0).
    # T2 = camera->marker: translation (0, 0, 2), no rotation (the marker 2 m in front).
    # T3 = world->marker: translation (0.5, 0, 0).
    # T = T1 T2 T3^-1: T2 T3^-1 = translation (-0.5, 0, 2); rotated by 90 deg about z: (0, -0.5, 2);
    # plus (1, 0, 0): T_drone_world = translation (1, -0.5, 2), rotation 90 deg about z.
    _, _, listener = make(HAND)
    md = MarkerData(1, 5, 0.01, (0.0, 0.0, 2.0), (1.0, 0.0, 0.0, 0.0), 0)
    edge = listener.edge_from(md)
    assert edge.observer == "drone" and edge.observed == "world"
    np.testing.assert_allclose(edge.p_a_b, [1.0, -0.5, 2.0], atol=1e-12)
    expected = Rotation.from_euler("z", 90, degrees=True)
    assert (Rotation.from_quat(edge.q_a_b_xyzw).inv() * expected).magnitude() < 1e-12


def test_downward_camera_localizes_drone_from_floor_tags():
    world, graph, listener = make(
        {
            "entities": {
                "world": {
                    "markers": [
                        {"id": 0, "size_m": 0.18, "pose": {"pos": [0, 0, 0]}},
                        {"id": 1, "size_m": 0.18, "pose": {"pos": [1, 0, 0], "rpy_deg": [0, 0, 30]}},
                    ]
                },
                "drone": {
                    "sensors": [{"name": "down", "id": 1, "pose": {"pos": [0.2, 0, -0.05], "rpy_deg": [0, 90, 0]}}]
                },
            }
        }
    )
    truth = {"world": RigidTransform.identity(), "drone": pose([0.4, 0.3, 1.5], [3, -4, 120])}
    for marker in (0, 1):
        assert listener.accept(observe(world, truth, 1, marker), now_ns=0) is None
    result = graph.evaluate(0)
    d = result.poses["drone"]
    assert d.n_observations == 2
    assert_pose_close(d.p_world_m, d.q_world_xyzw, truth["drone"], 1e-9, 1e-9)


def test_world_fixed_camera_observes_a_drone_marker():
    world, graph, listener = make(
        {
            "conventions": {"world": "NED", "body": "FRD"},
            "entities": {
                "world": {
                    "sensors": [{"name": "corner", "id": 9, "pose": {"pos": [-3, -3, -2.5], "rpy_deg": [0, -30, 45]}}]
                },
                "drone": {
                    "markers": [{"id": 40, "size_m": 0.1, "pose": {"pos": [0, 0, -0.05], "rpy_deg": [180, 0, 0]}}]
                },
            },
        }
    )
    # Truth is internal ENU/FLU: the NED/FRD file was normalised at load.
    truth = {"world": RigidTransform.identity(), "drone": pose([0.5, -0.2, 1.0], [0, 0, -20])}
    assert listener.accept(observe(world, truth, 9, 40), now_ns=0) is None
    d = graph.evaluate(0).poses["drone"]
    assert d.level == 1
    assert_pose_close(d.p_world_m, d.q_world_xyzw, truth["drone"], 1e-9, 1e-9)


def test_ema_filters_each_edge_and_restarts_after_expiry():
    _, graph, listener = make(HAND, alpha=0.5)
    first = MarkerData(1, 5, 0.01, (0.0, 0.0, 2.0), (1.0, 0.0, 0.0, 0.0), 0)
    second = replace(first, p_sensor_marker_m=(0.0, 0.0, 3.0))
    listener.accept(first, now_ns=0)
    listener.accept(second, now_ns=100 * MS)
    # T_drone_world z: 2 then 3 -> EMA with alpha 0.5 gives 2.5 (eq. 3).
    assert graph.edges[(1, 5)].p_a_b[2] == pytest.approx(2.5)
    listener.accept(first, now_ns=100 * MS + 250 * MS + 1)  # the edge expired meanwhile: start afresh
    assert graph.edges[(1, 5)].p_a_b[2] == pytest.approx(2.0)


def test_ema_is_sign_safe_on_incoming_quaternions():
    _, graph, listener = make(HAND, alpha=0.5)
    q = Rotation.from_euler("y", 20, degrees=True).as_quat()
    w, x, y, z = q[3], q[0], q[1], q[2]
    listener.accept(MarkerData(1, 5, 0.01, (0, 0, 2), (w, x, y, z), 0), 0)
    listener.accept(MarkerData(1, 5, 0.01, (0, 0, 2), (-w, -x, -y, -z), 0), MS)
    edge_before = listener.edge_from(MarkerData(1, 5, 0.01, (0, 0, 2), (w, x, y, z), 0))
    got = Rotation.from_quat(graph.edges[(1, 5)].q_a_b)
    assert (got.inv() * Rotation.from_quat(edge_before.q_a_b_xyzw)).magnitude() < 1e-9


GOOD = MarkerData(1, 5, 0.01, (0.0, 0.0, 2.0), (1.0, 0.0, 0.0, 0.0), 0)


@pytest.mark.parametrize(
    ("bad", "reason"),
    [
        (replace(GOOD, p_sensor_marker_m=(math.nan, 0.0, 2.0)), Rejection.NON_FINITE),
        (replace(GOOD, p_sensor_marker_m=(math.inf, 0.0, 2.0)), Rejection.NON_FINITE),
        (replace(GOOD, q_sensor_marker_wxyz=(math.nan, 0.0, 0.0, 1.0)), Rejection.NON_FINITE),
        (replace(GOOD, sigma_m=math.nan), Rejection.NON_FINITE),
        (replace(GOOD, q_sensor_marker_wxyz=(0.0, 0.0, 0.0, 0.0)), Rejection.ZERO_QUATERNION),
        (replace(GOOD, sigma_m=0.0), Rejection.BAD_SIGMA),
        (replace(GOOD, sigma_m=-0.01), Rejection.BAD_SIGMA),
        (replace(GOOD, sigma_m=1e30), Rejection.BAD_SIGMA),
        (replace(GOOD, p_sensor_marker_m=(0.0, 0.0, 1e7)), Rejection.OUT_OF_RANGE),
        (replace(GOOD, p_sensor_marker_m=(1e308, 1e308, 2.0)), Rejection.OUT_OF_RANGE),  # finite, sum is not
        (replace(GOOD, p_sensor_marker_m=(math.inf, -math.inf, 2.0)), Rejection.NON_FINITE),
        (replace(GOOD, covariance=(1e-6,) * 20 + (math.inf,)), Rejection.BAD_COVARIANCE),
        (replace(GOOD, covariance=(1e-6,) * 20 + (math.nan,)), Rejection.BAD_COVARIANCE),
        (replace(GOOD, covariance=(1e308,) * 21), Rejection.BAD_COVARIANCE),  # finite; singular: the listener's
        (replace(GOOD, sensor_id=77), Rejection.UNKNOWN_SENSOR),
        (replace(GOOD, marker_id=77), Rejection.UNKNOWN_MARKER),
    ],
)
def test_each_rejection_is_counted_and_changes_nothing(bad, reason):
    _, graph, listener = make(HAND)
    listener.accept(GOOD, now_ns=0)
    edge = graph.edges[(1, 5)]
    before = (edge.p_a_b.copy(), edge.q_a_b.copy(), edge.stamp_ns)
    assert listener.accept(bad, now_ns=10 * MS) is reason
    assert listener.rejected[reason] == 1
    assert sum(listener.rejected.values()) == 1
    assert listener.accepted == 1
    edge = graph.edges[(1, 5)]
    np.testing.assert_array_equal(edge.p_a_b, before[0])
    np.testing.assert_array_equal(edge.q_a_b, before[1])
    assert edge.stamp_ns == before[2]
    assert len(graph.edges) == 1


def test_marker_on_the_observers_own_entity_is_rejected():
    _, graph, listener = make(
        {
            "entities": {
                "drone": {
                    "sensors": [{"name": "cam", "id": 1, "pose": {"pos": [0, 0, 0]}}],
                    "markers": [{"id": 3, "size_m": 0.1, "pose": {"pos": [0, 0, 0.1]}}],
                }
            }
        }
    )
    assert listener.accept(replace(GOOD, marker_id=3), 0) is Rejection.OWN_MARKER
    assert listener.rejected[Rejection.OWN_MARKER] == 1
    assert graph.edges == {}


def test_forget_expired_bounds_filter_state():
    _, _, listener = make(HAND, alpha=0.5)
    listener.accept(GOOD, 0)
    listener.forget_expired(250 * MS)
    assert len(listener._ema) == 1
    listener.forget_expired(250 * MS + 1)
    assert len(listener._ema) == 0


def test_with_age_sigma_each_edge_is_a_kalman_filter():
    """Beyond the paper: a blurred frame (large sigma) cannot overwrite a sharp one taken just before."""
    world = world_from({**HAND, "fusion": {"age_sigma_m_per_s": 1.0}})
    graph = make_graph(world)
    listener = Listener(world, graph)
    sharp = MarkerData(1, 5, 0.001, (0.0, 0.0, 2.0), (1.0, 0.0, 0.0, 0.0), 0)
    blurred = replace(sharp, sigma_m=0.1, p_sensor_marker_m=(0.0, 0.0, 2.3))
    listener.accept(sharp, now_ns=0)
    listener.accept(blurred, now_ns=20 * MS)
    # old variance: 0.001^2 + (0.02 s * 1 m/s)^2 = 4.01e-4; new: 0.01 -> alpha = 4.01e-4 / 1.0401e-2
    var_old, var_new = 0.001**2 + 0.02**2, 0.1**2
    alpha = var_old / (var_old + var_new)
    edge = graph.edges[(1, 5)]
    assert edge.p_a_b[2] == pytest.approx(2.0 + alpha * 0.3, rel=1e-9)
    assert edge.sigma_m == pytest.approx(np.sqrt(var_old * var_new / (var_old + var_new)))


def test_a_record_with_its_own_covariance_replaces_its_edge_and_keeps_it():
    """A record carrying the detector's 6x6 replaces its edge even with age_sigma (no scalar blend),
    and the edge's covariance is that 6x6 carried through eq. 1's mountings, not the sigma model."""
    from atlas_onboard.core import covariance
    from atlas_onboard.core.markerdata import matrix_to_upper

    world = world_from({**HAND, "fusion": {"age_sigma_m_per_s": 1.0}})
    graph = make_graph(world)
    listener = Listener(world, graph)
    C_sm = np.diag([1e-8, 1e-8, 4e-6, 3e-4, 3e-4, 1e-6])
    C_sm[0, 4] = C_sm[4, 0] = 1e-6  # a lateral-tilt correlation, to see it carried
    sharp = MarkerData(1, 5, 0.001, (0.0, 0.0, 2.0), (1.0, 0.0, 0.0, 0.0), 0, covariance=matrix_to_upper(C_sm))
    second = replace(sharp, sigma_m=0.1, p_sensor_marker_m=(0.0, 0.0, 2.3))
    listener.accept(sharp, now_ns=0)
    listener.accept(second, now_ns=20 * MS)
    edge = graph.edges[(1, 5)]
    np.testing.assert_allclose(edge.p_a_b, listener.edge_from(second).p_a_b, atol=1e-12)  # replaced
    T1 = world.sensors[1].T_entity_sensor.as_matrix()
    T3_inv = world.markers[5].T_entity_marker.inv().as_matrix()
    # The record's T_s_m is a pure translation: R_sm = I.
    chain = covariance.Chain(T1[None, :3, :3], np.eye(3)[None], np.array([[0.0, 0.0, 2.3]]), T3_inv[None])
    expected = covariance.detection(chain, C_sm[None])[0]
    np.testing.assert_allclose(graph.edges[(1, 5)].cov_a_b, expected, rtol=1e-12, atol=1e-18)
    model = listener.edge_from(replace(second, covariance=())).cov_a_b
    assert model[0, 0] > 100 * expected[0, 0]  # the sigma model: the isotropic camera position, far wider


# --- planar ambiguity ------------------------------------------------------------------------------

AMB = {
    "entities": {
        "world": {
            "markers": [
                {"id": 5, "size_m": 0.15, "pose": {"pos": [0.5, 0, 0]}},
                {"id": 6, "size_m": 0.15, "pose": {"pos": [-0.5, 0.3, 0], "rpy_deg": [0, 0, 40]}},
            ]
        },
        "drone": {"sensors": [{"name": "down", "id": 1, "pose": {"pos": [0.2, 0, -0.05], "rpy_deg": [0, 90, 0]}}]},
    }
}


def ambiguous_scene(estimate_error_deg: float = 2.0):
    """A drone 4 m from world marker 5, seen 15 degrees from face-on so that IPPE's chosen solution is
    the flip; the drone's estimate comes from an unambiguous observation of marker 6 with an error."""
    from tests.core.test_ambiguity import T_TRUE, flipped_seed, ippe

    world, graph, listener = make(AMB)
    T_drone_sensor = world.sensors[1].T_entity_sensor
    truth = {
        "world": RigidTransform.identity(),
        "drone": world.markers[5].T_entity_marker * T_TRUE.inv() * T_drone_sensor.inv(),
    }
    a, b, ratio, sigma = ippe(T_TRUE, 0.3, flipped_seed())
    qa, qb = a.rotation.as_quat(), b.rotation.as_quat()
    md = MarkerData(
        1, 5, sigma, tuple(a.translation), (qa[3], *qa[:3]), 0, 0.5, ratio,
        p_sensor_marker_alt_m=tuple(b.translation), q_sensor_marker_alt_wxyz=(qb[3], *qb[:3]),
    )  # fmt: skip
    noise = RigidTransform.from_rotation(
        Rotation.from_euler("xz", [estimate_error_deg, -estimate_error_deg], degrees=True)
    )
    bootstrap = observe(world, truth, 1, 6, T_noise=noise)
    return world, graph, listener, truth, md, bootstrap


def test_ambiguous_flip_becomes_the_true_edge_given_estimates():
    _, graph, listener, truth, md, bootstrap = ambiguous_scene()
    T_true_edge = truth["drone"].inv()  # T_drone_world
    flipped = listener.edge_from(md)  # no estimates yet: unresolved
    assert flipped is Rejection.AMBIGUITY_UNRESOLVED
    assert listener.accept(bootstrap, now_ns=0) is None
    listener.set_estimates(graph.evaluate(0).poses)
    edge = listener.edge_from(md)
    assert isinstance(edge, EdgeUpdate)
    # It is eq. 1 on the other solution, exactly, and the flip it replaced was far from the truth.
    alt = listener.edge_from(replace(md, ambiguity_ratio=0.0, p_sensor_marker_m=md.p_sensor_marker_alt_m,
                                     q_sensor_marker_wxyz=md.q_sensor_marker_alt_wxyz))  # fmt: skip
    primary = listener.edge_from(replace(md, ambiguity_ratio=0.0))
    np.testing.assert_allclose(edge.p_a_b, alt.p_a_b, atol=1e-12)
    err = lambda e: np.degrees((Rotation.from_quat(e.q_a_b_xyzw).inv() * T_true_edge.rotation).magnitude())  # noqa: E731
    assert err(primary) > 10.0 > err(edge)

    # Where that puts the drone in the world (eq. 1 inverted swings it by range x angle).
    def drone_error_m(e):
        T_world_drone = RigidTransform.from_components(e.p_a_b, Rotation.from_quat(e.q_a_b_xyzw)).inv()
        return float(np.linalg.norm(T_world_drone.translation - truth["drone"].translation))

    assert drone_error_m(edge) < 0.2 < drone_error_m(primary)
    # Accepted through the hot path: counted, and the graph's edge is the resolved one.
    assert listener.accept_many([(md, 1 * MS)]) == [None]
    assert listener.counters["ambiguity_resolved"] == 1 and listener.counters["ambiguity_swapped"] == 1
    np.testing.assert_allclose(graph.edges[(1, 5)].p_a_b, alt.p_a_b, atol=1e-12)


def test_ambiguous_without_estimates_is_rejected_and_counted():
    _, graph, listener, _, md, _ = ambiguous_scene()
    assert listener.accept_many([(md, 0)]) == [Rejection.AMBIGUITY_UNRESOLVED]
    assert listener.rejected[Rejection.AMBIGUITY_UNRESOLVED] == 1
    assert listener.counters["ambiguity_no_prediction"] == 1
    assert graph.edges == {}


def test_ambiguous_with_an_estimate_far_off_is_rejected_as_both_far():
    _, graph, listener, _, md, bootstrap = ambiguous_scene(estimate_error_deg=60.0)
    listener.accept(bootstrap, now_ns=0)
    listener.set_estimates(graph.evaluate(0).poses)
    assert listener.accept(md, 1 * MS) is Rejection.AMBIGUITY_UNRESOLVED
    assert listener.counters["ambiguity_both_far"] == 1
    assert (1, 5) not in graph.edges


def test_ambiguous_without_the_other_solution_is_rejected_as_before():
    _, graph, listener, _, md, _ = ambiguous_scene()
    bare = replace(md, p_sensor_marker_alt_m=(math.nan,) * 3, q_sensor_marker_alt_wxyz=(math.nan,) * 4)
    assert listener.accept(bare, 0) is Rejection.AMBIGUOUS
    assert listener.rejected[Rejection.AMBIGUOUS] == 1 and graph.edges == {}


@pytest.mark.parametrize(
    ("p_alt", "q_alt"),
    [
        ((math.nan, 0.0, 2.0), (1.0, 0.0, 0.0, 0.0)),  # partly NaN
        ((0.0, 0.0, math.inf), (1.0, 0.0, 0.0, 0.0)),
        ((0.0, 0.0, 2.0), (0.0, 0.0, 0.0, 0.0)),  # zero quaternion
        ((0.0, 0.0, 1e7), (1.0, 0.0, 0.0, 0.0)),  # out of range
    ],
)
def test_an_unusable_other_solution_is_ignored_and_counted(p_alt, q_alt):
    _, _, listener = make(HAND)
    clear = replace(GOOD, ambiguity_ratio=0.1, p_sensor_marker_alt_m=p_alt, q_sensor_marker_alt_wxyz=q_alt)
    assert listener.accept(clear, 0) is None  # the primary solution stands on its own
    assert listener.counters["alt_ignored"] == 1
    assert listener.accept(replace(clear, ambiguity_ratio=0.9), MS) is Rejection.AMBIGUOUS
    assert listener.counters["alt_ignored"] == 2 and listener.rejected[Rejection.AMBIGUOUS] == 1


def test_a_batch_resolves_exactly_as_one_by_one():
    _, graph, listener, _, md, bootstrap = ambiguous_scene()
    listener.accept(bootstrap, 0)
    listener.set_estimates(graph.evaluate(0).poses)
    batch = [md, bootstrap, replace(md, ambiguity_ratio=0.2), replace(md, marker_id=77), md]
    one_by_one = [listener.edge_from(m) for m in batch]
    together, _ = listener._edges(batch)
    for x, y in zip(one_by_one, together, strict=True):
        if isinstance(x, Rejection):
            assert x is y
        else:
            np.testing.assert_allclose(x.p_a_b, y.p_a_b, atol=1e-12)
            np.testing.assert_allclose(x.q_a_b_xyzw, y.q_a_b_xyzw, atol=1e-12)


@pytest.mark.parametrize(("age_ms", "resolved"), [(0, True), (20, True), (500, False)])
def test_a_stale_estimate_cannot_resolve_an_ambiguity(age_ms, resolved):
    """The prediction widens with what the drone may have turned and moved since its estimate was
    captured (3 rad/s, 3 m/s): a fresh one still picks the true solution, one half a second old
    leaves the observation undecided (rejected, counted) rather than risk the flip."""
    _, graph, listener, _, md, bootstrap = ambiguous_scene()
    listener.accept(bootstrap, now_ns=0)
    listener.set_estimates(graph.evaluate(0).poses)
    late = replace(md, capture_time_us=md.capture_time_us + age_ms * 1000)
    reason = listener.accept(late, 1 * MS)
    assert (reason is None) == resolved
    if not resolved:
        assert reason is Rejection.AMBIGUITY_UNRESOLVED and (1, 5) not in graph.edges


def test_a_covariance_that_is_not_positive_definite_is_rejected_and_the_rest_of_the_batch_kept():
    from atlas_onboard.core.markerdata import matrix_to_upper

    _, graph, listener = make(HAND)
    good = np.diag([1e-6, 1e-6, 4e-6, 1e-4, 1e-4, 1e-6])
    bad = good.copy()
    bad[0, 3] = bad[3, 0] = 2e-5  # |correlation| 2: positive variances, not positive definite
    ok = MarkerData(1, 5, 0.01, (0.0, 0.0, 2.0), (1.0, 0.0, 0.0, 0.0), 0, covariance=matrix_to_upper(good))
    wrong = replace(ok, seq=1, covariance=matrix_to_upper(bad))
    assert wrong.rejection() is None  # on its own it looks plausible: the listener checks the matrix
    reasons = listener.accept_many([(wrong, 0), (ok, 0)])
    assert reasons == [Rejection.BAD_COVARIANCE, None]
    assert listener.rejected[Rejection.BAD_COVARIANCE] == 1 and listener.accepted == 1
    np.testing.assert_allclose(graph.edges[(1, 5)].p_a_b, listener.edge_from(ok).p_a_b)


def test_a_record_is_judged_on_its_numbers_not_on_whether_their_sum_overflows():
    # rejection() sums the numbers to test them all at once; a finite but huge sum must not pass
    # for a non-finite one (the covariance's matrix is the listener's to check: this one is singular).
    assert replace(GOOD, covariance=(1e308,) * 21).rejection() is None
    assert replace(GOOD, p_sensor_marker_m=(1e308, 1e308, 0.0)).rejection() is Rejection.OUT_OF_RANGE


def test_a_swapped_record_gets_the_sigma_models_covariance_not_the_one_its_detector_gave_the_other_pose():
    from atlas_onboard.core.markerdata import matrix_to_upper

    _, graph, listener, _, md, bootstrap = ambiguous_scene()
    detector_cov = np.diag([1e-8, 1e-8, 1e-6, 1e-6, 1e-6, 1e-8])  # the chosen (flipped) solution's
    md = replace(md, covariance=matrix_to_upper(detector_cov))
    listener.accept(bootstrap, now_ns=0)
    listener.set_estimates(graph.evaluate(0).poses)
    assert listener.accept_many([(md, 1 * MS)]) == [None] and listener.counters["ambiguity_swapped"] == 1
    alt = replace(md, ambiguity_ratio=0.0, p_sensor_marker_m=md.p_sensor_marker_alt_m,
                  q_sensor_marker_wxyz=md.q_sensor_marker_alt_wxyz)  # fmt: skip
    modelled = listener.edge_from(replace(alt, covariance=())).cov_a_b
    carried = listener.edge_from(alt).cov_a_b
    assert not np.allclose(modelled, carried)
    np.testing.assert_allclose(graph.edges[(1, 5)].cov_a_b, modelled, rtol=1e-12)
