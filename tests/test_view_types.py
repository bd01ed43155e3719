"""`nhfd.views.View` (issue 33): a view is a value, checked in its constructor, parsed once at
the RPC edge (`nhfd.daemon.views.parse_view`), and shown in the JSON form views had as dicts."""

from __future__ import annotations

import math
import pickle

import pytest

from nhfd.daemon.protocol import Params, RpcError
from nhfd.daemon.views import ViewSlot, parse_view
from nhfd.views import Orbit, Pose, View, view_from_json

ORBIT = View(Orbit(10.0, 20.0, 0.7), refocus_mm=1.5)
POSE = View(Pose((0.1, -0.2, 0.3), (1.0, 0.0, 0.0, 0.0)))


@pytest.mark.parametrize(("make", "message"), [
    (lambda: Orbit(361.0, 0.0, 1.0), r"view azimuth_deg = 361\.0: expected a finite number in "
                                     r"\[-360, 360\] deg"),
    (lambda: Orbit(math.nan, 0.0, 1.0), r"view azimuth_deg = nan"),
    (lambda: Orbit(0.0, 90.0, 1.0), r"view elevation_deg = 90\.0: .* in \[-89\.9, 89\.9\] deg"),
    (lambda: Orbit(0.0, 0.0, 0.0), r"view radius = 0\.0: .* in \(0, 1e\+06\] scene units"),
    (lambda: Orbit(0.0, 0.0, True), r"view radius = True"),  # a bool is not a number
    (lambda: Pose((0.0, 0.0), (1.0, 0.0, 0.0, 0.0)), r"view position = \[0\.0, 0\.0\]: "
                                                     r"expected 3 coordinates"),
    (lambda: Pose((2e6, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)), r"view position\[0\] = 2000000\.0"),
    (lambda: Pose((0.0, 0.0, 0.0), (2.0, 0.0, 0.0, 0.0)), r"view quaternion_wxyz = \[2\.0, "
                                                          r"0\.0, 0\.0, 0\.0\]: norm 2"),
    (lambda: Pose((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)), r"expected 4 finite numbers"),
    (lambda: View(Orbit(0.0, 0.0, 1.0), refocus_mm=11.0), r"view refocus_mm = 11\.0: .* in "
                                                          r"\[-10, 10\] mm"),
    (lambda: View({"kind": "orbit"}), r"view camera = .*: expected an Orbit or a Pose"),
])
def test_the_constructors_refuse_a_value_out_of_range_naming_it_and_the_range(make, message):
    with pytest.raises(ValueError, match=message):
        make()


def test_a_view_is_hashable_and_its_sequences_are_tuples():
    # The worker's frame cache keys on the view: equal views must be one key, whatever
    # sequence type built them, and nothing may change a view under its holder.
    a = View(Pose([0.1, -0.2, 0.3], [1.0, 0.0, 0.0, 0.0]))
    assert a == POSE and hash(a) == hash(POSE)
    assert isinstance(a.camera.position, tuple) and isinstance(a.camera.quaternion_wxyz, tuple)
    assert {a: 1}[POSE] == 1
    assert ORBIT != ORBIT.with_refocus(0.0)  # the refocus is part of the view
    with pytest.raises(AttributeError):
        ORBIT.refocus_mm = 2.0  # type: ignore[misc]


def test_the_json_form_is_the_dict_views_were_and_parses_back():
    assert ORBIT.to_json() == {"kind": "orbit", "azimuth_deg": 10.0, "elevation_deg": 20.0,
                               "radius": 0.7, "refocus_mm": 1.5}
    assert POSE.to_json() == {"kind": "pose", "position": [0.1, -0.2, 0.3],
                              "quaternion_wxyz": [1.0, 0.0, 0.0, 0.0], "refocus_mm": 0.0}
    for view in (ORBIT, POSE):
        assert view_from_json(view.to_json()) == view
        assert pickle.loads(pickle.dumps(view)) == view  # as it crosses the worker's pipe
    assert view_from_json({"kind": "orbit", "azimuth_deg": 1, "elevation_deg": 2,
                           "radius": 3}).refocus_mm == 0.0
    with pytest.raises(ValueError, match=r"view kind = 'spin': expected \"orbit\" or \"pose\""):
        view_from_json({"kind": "spin"})
    with pytest.raises(ValueError, match=r"view: a pose view needs quaternion_wxyz"):
        view_from_json({"kind": "pose", "position": [0, 0, 0]})


def test_parse_view_returns_a_view_that_keeps_the_refocus_until_given():
    first = parse_view(Params({"orbit": {"azimuth_deg": 190.0, "elevation_deg": 5.0,
                                         "radius": 2.0}, "refocus_mm": 2.5}), None)
    assert first == View(Orbit(-170.0, 5.0, 2.0), refocus_mm=2.5)  # the azimuth wrapped
    moved = parse_view(Params({"relative": {"d_azimuth_deg": 20.0}}), first)
    assert moved == View(Orbit(-150.0, 5.0, 2.0), refocus_mm=2.5)  # refocus kept
    pose = parse_view(Params({"pose": {"position": [0, 0, -2],
                                       "quaternion_wxyz": [2.0, 0, 0, 0]}}), moved)
    assert pose.camera == Pose((0.0, 0.0, -2.0), (1.0, 0.0, 0.0, 0.0))  # normalised here
    assert pose.refocus_mm == 2.5
    turned = parse_view(Params({"relative": {"translate": [0.0, 0.0, 1.0]},
                                "refocus_mm": 0.0}), pose)
    assert turned.camera.position == (0.0, 0.0, -1.0) and turned.refocus_mm == 0.0


def test_parse_view_keeps_todays_messages():
    # The refocus is read first, as set_view read it before the view.
    with pytest.raises(RpcError, match=r"refocus_mm"):
        parse_view(Params({"refocus_mm": 99.0}), None)
    with pytest.raises(RpcError, match=r"orbit\|pose\|relative"):
        parse_view(Params({}), None)
    with pytest.raises(RpcError, match=r"pose\.quaternion_wxyz"):
        parse_view(Params({"pose": {"position": [0, 0, 0], "quaternion_wxyz": [9e-3, 0, 0, 0]}}),
                   None)
    with pytest.raises(RpcError, match=r"relative"):
        parse_view(Params({"relative": {}}), None)


def test_the_view_slot_shows_the_json_form():
    slot = ViewSlot()
    assert slot.snapshot()["requested"] is None
    seq = slot.submit(ORBIT)
    assert slot.latest_after(0, 0.0) == (seq, ORBIT)
    assert slot.snapshot()["requested"] == ORBIT.to_json()


def test_a_views_quality_tier_is_checked_and_shown_only_above_network() -> None:
    from nhfd.views import QUALITY_TIERS, Orbit, View, view_from_json

    cam = Orbit(10.0, 5.0, 2.0)
    plain = View(cam)
    assert plain.quality == "network" and "quality" not in plain.to_json()
    sgd = plain.with_quality("sgd")
    assert sgd.to_json()["quality"] == "sgd" and view_from_json(sgd.to_json()) == sgd
    assert view_from_json(plain.to_json()) == plain
    assert sgd != plain and hash(sgd) != hash(plain)  # the worker's cache keys on views
    with pytest.raises(ValueError, match="view quality = 'best': expected one of network, "
                                         "exact, sgd, citl"):
        View(cam, quality="best")
    assert QUALITY_TIERS == ("network", "exact", "sgd", "citl")
