"""The camera-view convention of episode stores (iwsim.data.views) and how imports name
another format's cameras (iwsim.data.formats.common)."""

from __future__ import annotations

import numpy as np
import pytest

from iwsim.core.errors import InputError
from iwsim.data import views
from iwsim.data.formats import common
from iwsim.data.formats.common import SourceViews, view_name


@pytest.mark.parametrize("cameras, message", [
    ([], "name at least one camera"),
    (["top", "Side"], "camera name 'Side' must be 1-32 lower-case letters"),
    (["top", "_side"], "camera name '_side' must be"),
    (["a" * 33], "must be 1-32"),
    (["top", ""], "camera name '' must be"),
    (["top", 3], "camera name 3 must be"),
    (["top", "side", "top"], r"must be distinct, got \['top', 'side', 'top'\]"),
])
def test_check_cameras_refuses_bad_names(cameras, message):
    with pytest.raises(InputError, match=message) as e:
        views.check_cameras(cameras, "cameras")
    assert "\n" not in str(e.value) and str(e.value).startswith("cameras: ")


def test_check_and_parse_cameras():
    assert views.check_cameras(["top", "side_2", "0cam"]) == ("top", "side_2", "0cam")
    assert views.check_cameras(iter(["top"])) == ("top",)
    assert views.parse_cameras("top, side") == ("top", "side")
    with pytest.raises(InputError, match="^--cameras: camera names must be distinct"):
        views.parse_cameras("top,top")


def test_view_keys():
    cams = ("top", "side", "wrist")
    assert views.view_key(cams, "top") == "img"
    assert views.view_key(cams, "side") == "img_side"
    assert views.view_keys(cams) == {"top": "img", "side": "img_side", "wrist": "img_wrist"}
    assert list(views.view_keys(("side", "top"))) == ["side", "top"]  # view order
    assert views.view_keys(("side", "top"))["top"] == "img_top"
    with pytest.raises(InputError, match="no camera 'front'; the views are top, side, wrist"):
        views.view_key(cams, "front")


def test_store_cameras_defaults_and_checks():
    assert views.store_cameras({}) == (views.DEFAULT_CAMERA,) == ("top",)  # a store written before views
    assert views.store_cameras({"camera": "observation.images.wrist"}) == ("wrist",)  # an import's one camera
    assert views.store_cameras({"camera": "agentview_image"}) == ("agentview_image",)
    assert views.store_cameras({"camera": "img_side"}) == ("side",)  # one view of a store, imported alone
    assert views.store_cameras({"camera": "Bad Name!"}) == ("top",)
    assert views.store_cameras({"camera": 3}) == ("top",)
    assert views.store_cameras({"cameras": ["top", "side"], "camera": "x"}) == ("top", "side")
    assert views.store_cameras({"cameras": ["top", "side"]}, ["img", "img_side", "state"]) == ("top", "side")
    with pytest.raises(InputError, match=r"names the views \['top', 'side'\] but holds no img_side"):
        views.store_cameras({"cameras": ["top", "side"]}, ["img", "state"])
    with pytest.raises(InputError, match="must list camera names, got 'top'"):
        views.store_cameras({"cameras": "top"})
    with pytest.raises(InputError, match="camera names must be distinct"):
        views.store_cameras({"cameras": ["top", "top"]})


def test_split_and_first_view():
    a, b = np.zeros((2, 2, 3), np.uint8), np.ones((2, 2, 3), np.uint8)
    assert views.split_views(a, ("top",))["top"] is a
    assert list(views.split_views({"side": b, "top": a}, ("top", "side"))) == ["top", "side"]
    with pytest.raises(InputError, match="expected the views"):
        views.split_views({"top": a}, ("top", "side"))
    with pytest.raises(InputError, match="as a mapping, got one array"):
        views.split_views(a, ("top", "side"))
    assert views.first_view({"top": a, "side": b}) is a and views.first_view(b) is b


@pytest.mark.parametrize("source, prefixes, suffixes, name", [
    ("observation.images.wrist_left", (), (), "wrist_left"),
    ("observation.image", (), (), "image"),
    ("agentview_image", (), ("_image",), "agentview"),
    ("_image", (), ("_image",), "image"),  # nothing would remain: kept
    ("img_wrist", ("img_",), ("_image", "_img"), "wrist"),
    ("Cam-High (left)", (), (), "cam_high_left"),
    ("!!!", (), (), "camera"),
    ("x" * 40, (), (), "x" * 32),
])
def test_view_name(source, prefixes, suffixes, name):
    assert view_name(source, prefixes, suffixes) == name
    views.check_cameras([name])


def test_source_views():
    v = SourceViews.of(["observation.images.top", "observation.images.side"])
    assert v.names == ("top", "side")
    assert v.keys == {"observation.images.top": "img", "observation.images.side": "img_side"}
    assert v.attrs() == {"cameras": ["top", "side"],
                         "source_cameras": ["observation.images.top", "observation.images.side"]}
    one = SourceViews.of(["observation.images.side"])
    assert one.keys == {"observation.images.side": "img"} and one.attrs() == {"camera": "observation.images.side"}
    clash = SourceViews.of(["img_side", "side_image", "Side"], prefixes=("img_",), suffixes=("_image",))
    assert clash.names == ("side", "side_2", "side_3")
    long = SourceViews.of(["a" * 40, "a" * 33])
    assert long.names == ("a" * 32, "a" * 30 + "_2")


def test_resize_memory_counts_every_view(monkeypatch):
    asked = []
    monkeypatch.setattr(common, "require_memory", lambda need, what: asked.append(need))
    common.check_resize_memory(10, 8, "x")
    common.check_resize_memory(10, 8, "x", n_views=3)
    assert asked[1] == 3 * asked[0] == 3 * 10 * 8 * 8 * 3 * common.RESIZE_BYTES_PER_VALUE


def test_imports_count_every_view_when_resizing(two_view_store, tmp_path, monkeypatch):
    from iwsim.data.formats import import_

    asked = []
    monkeypatch.setattr(common, "require_memory", lambda need, what: asked.append((need, what)))
    import_("zarr", two_view_store, tmp_path / "s.zarr", image_size=16, progress=False)
    frame = 16 * 16 * 3 * common.RESIZE_BYTES_PER_VALUE
    assert (2 * frame, "--image-size 16 (for a single frame of 2 views)") in asked
    assert (5 * 2 * frame, "resizing an episode of 5 frames of 2 views to 16x16") in asked
