"""The builders of the field's parts from the config: every Tracker knob comes from it."""

from __future__ import annotations

import inspect

from cpslam.common.camera import Intrinsics
from cpslam.common.config import load_config
from cpslam.common.field.tracking import Tracker
from cpslam.common.field_config import sampler_from_config, tracker_args_from_config
from cpslam.server.loops import PoseRefiner


def test_tracker_args_cover_every_tracker_keyword() -> None:
    cfg = load_config("cpu", env={})
    args = tracker_args_from_config(cfg.field, cfg.tracking)
    # reuse_neighbours (how often the neighbour search is redone) is a speed setting, no field.
    keywords = set(inspect.signature(Tracker.__init__).parameters) - {
        "self", "intrinsics", "sampler", "reuse_neighbours"}
    assert set(args) == keywords  # a new Tracker knob must be read from the config here
    tracker = Tracker(Intrinsics(64.0, 64.0, 39.5, 29.5, 80, 60), sampler_from_config(cfg.field),
                      **args)
    assert tracker.pixel_sampling == cfg.tracking.pixel_sampling == "stratified"
    assert tracker.n_pixels == cfg.tracking.n_pixels and tracker.radius == cfg.field.radius


def test_loop_refiner_tracks_as_the_agents_do_with_its_own_steps() -> None:
    cfg = load_config("cpu", overrides=["loop.register_iters=17"], env={})
    refiner = PoseRefiner.from_config(cfg, registry=None)
    expected = {**tracker_args_from_config(cfg.field, cfg.tracking), "iters": 17}
    assert refiner.tracker_args == expected
