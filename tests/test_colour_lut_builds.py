"""The exact colour table built beside the loop (appliance/perception/rgbd_colour.py): one build
for every classifier of the same model that asks while it runs, and no build for a classifier
nobody holds any more (the suite made dozens of RGB-D pipelines and threw them away; each
orphaned build took 1-3 CPU-s from whatever ran next)."""
import gc
import threading

import numpy as np
import pytest

from appliance import rgbd_model
from appliance.perception import rgbd_colour
from appliance.perception.rgbd_colour import ColourClassifier


@pytest.fixture()
def gated(monkeypatch):
    """The background build (the one given ``wanted``) held at its start until the test opens
    the gate; a build in the caller's thread is not held."""
    gate = threading.Event()
    orig = ColourClassifier._build_lut

    def build(self, wanted=None):
        if wanted is not None:
            assert gate.wait(30.0), "the test never opened the gate"
        return orig(self, wanted)
    monkeypatch.setattr(ColourClassifier, "_build_lut", build)
    yield gate
    gate.set()


def _builders() -> set[threading.Thread]:
    return {t for t in threading.enumerate() if t.name == "rgbd-colour-lut"}


def _mixtures():
    return rgbd_model.load(None).mixtures("lab")


def test_two_classifiers_of_one_model_share_one_build(gated):
    before = _builders()
    a = ColourClassifier(_mixtures(), 3.3101, "lab", 8)
    b = ColourClassifier(_mixtures(), 3.3101, "lab", 8)
    started = _builders() - before
    assert len(started) == 1                            # one thread for both
    assert len(rgbd_colour._LUT_BUILDS[a._key]) == 2    # the second waits for the first's
    assert not a.lut_ready() and not b.lut_ready()
    gated.set()
    assert a.wait_lut(60.0) and b.wait_lut(60.0)
    assert a._lut is b._lut is rgbd_colour._LUT_CACHE[a._key]
    assert a._key not in rgbd_colour._LUT_BUILDS
    # and the table is the classifier's own answer, colour by colour
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
    want = a.classify(rgbd_colour.colour_features(img.reshape(-1, 3), "lab")).reshape(64, 64)
    assert np.array_equal(b.classify_image(img), want)
    next(iter(started)).join(5.0)


def test_a_dropped_classifier_stops_its_build_and_a_later_one_builds_again(gated):
    before = _builders()
    a = ColourClassifier(_mixtures(), 3.3102, "lab", 8)
    key = a._key
    (t,) = _builders() - before
    del a
    gc.collect()
    gated.set()
    t.join(10.0)                     # at its first look: nobody waits, so it stops
    assert not t.is_alive()
    assert key not in rgbd_colour._LUT_CACHE and key not in rgbd_colour._LUT_BUILDS
    c = ColourClassifier(_mixtures(), 3.3102, "lab", 8)
    assert c.wait_lut(60.0) and rgbd_colour._LUT_CACHE[key] is c._lut


def test_a_build_goes_on_while_one_of_its_waiters_lives(gated):
    a = ColourClassifier(_mixtures(), 3.3103, "lab", 8)
    b = ColourClassifier(_mixtures(), 3.3103, "lab", 8)
    del a                            # the one that started it
    gc.collect()
    gated.set()
    assert b.wait_lut(60.0) and b.lut_ready()


def test_a_classifier_asked_to_build_now_does_not_wait_for_one_in_flight(gated):
    a = ColourClassifier(_mixtures(), 3.3104, "lab", 8)                   # held at the gate
    b = ColourClassifier(_mixtures(), 3.3104, "lab", 8, background=False)  # built here
    assert b.lut_ready() and not a.lut_ready()
    gated.set()
    assert a.wait_lut(60.0)
    assert np.array_equal(a._lut, b._lut)
