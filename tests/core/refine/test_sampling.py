"""Which images a refining node's camera reports marker by marker."""

from atlas_onboard.core.refine.sampling import PerMarkerSchedule


def _images(schedule, stamps_us, seen):
    """Run the schedule over images with the markers ``seen`` in each; the images taken marker by marker."""
    taken = []
    for k, t in stamps_us:
        each = schedule.due(t)
        schedule.saw(t, each, seen)
        if each:
            taken.append(k)
    return taken


def test_one_image_per_half_second_is_reported_marker_by_marker():
    schedule = PerMarkerSchedule(frozenset({0, 1, 2}), period_us=500_000)
    frames = [(k, k * 66_667) for k in range(30)]  # 15 fps, 2 s
    # After an image with three world markers, then every 0.5 s or more.
    assert _images(schedule, frames, [0, 1, 2, 7]) == [1, 9, 17, 25]
    # Two world markers (7 is not one): nothing to refine from, every image joint.
    assert _images(schedule, [(k, k * 66_667) for k in range(30, 60)], [0, 1, 7]) == []


def test_a_clock_that_jumps_back_starts_the_period_again():
    schedule = PerMarkerSchedule(frozenset({0, 1, 2}), period_us=500_000)
    assert _images(schedule, [(0, 0), (1, 100_000), (2, 50_000), (3, 60_000)], [0, 1, 2]) == [1, 2]


def test_period_zero_takes_every_image_after_one_with_three_world_markers():
    schedule = PerMarkerSchedule(frozenset({0, 1, 2}), period_us=0)
    assert _images(schedule, [(k, k * 1000) for k in range(4)], [0, 1, 2]) == [1, 2, 3]
