"""The field spec and the tracker's and mapper's settings come from the config, whole."""

from __future__ import annotations

import dataclasses
import inspect

from cpslam.agent.mapper import Mapper
from cpslam.common.camera import Intrinsics
from cpslam.common.config import FieldConfig, load_config
from cpslam.common.field import FieldSpec
from cpslam.common.field.tracking import Tracker
from cpslam.common.field_config import (
    field_spec,
    mapper_args_from_config,
    tracker_args_from_config,
)
from cpslam.server.loops import PoseRefiner


def _keywords(cls: type, *skip: str) -> set[str]:
    return set(inspect.signature(cls.__init__).parameters) - {"self", *skip}


def test_field_spec_is_the_field_section() -> None:
    # A new `field` key must reach every part of the field through the spec.
    assert [f.name for f in dataclasses.fields(FieldSpec)] == list(FieldConfig.model_fields)
    cfg = load_config("cpu", env={})
    spec = field_spec(cfg.field)
    assert dataclasses.asdict(spec) == cfg.field.model_dump()
    decoders = spec.decoders(seed=3)
    assert decoders.c_out.out_features == cfg.field.c_hidden  # c_out null: C's hidden width
    assert spec.sampler().n_samples == cfg.field.n_near + cfg.field.n_uniform
    assert spec.point_map(0, "cpu").cell_size == cfg.field.grid_size
    paper = field_spec(load_config("paper", env={}).field)
    assert paper.decoders(seed=3).c_out.out_features == 128


def test_tracker_and_mapper_args_cover_every_keyword() -> None:
    cfg = load_config("cpu", env={})
    # reuse_neighbours (how often the neighbour search is redone) is a speed setting, no field.
    args = tracker_args_from_config(cfg.tracking)
    assert set(args) == _keywords(Tracker, "intrinsics", "spec", "reuse_neighbours")
    spec = field_spec(cfg.field)
    tracker = Tracker(Intrinsics(64.0, 64.0, 39.5, 29.5, 80, 60), spec, **args)
    assert tracker.pixel_sampling == cfg.tracking.pixel_sampling == "stratified"
    assert tracker.n_pixels == cfg.tracking.n_pixels and tracker.radius == cfg.field.radius
    args = mapper_args_from_config(cfg.mapping)
    assert set(args) == _keywords(Mapper, "spec")
    mapper = Mapper(spec, **args)
    assert mapper.k == cfg.field.k_neighbors and mapper.patch_size == cfg.field.patch_size


def test_loop_refiner_tracks_as_the_agents_do_with_its_own_steps() -> None:
    cfg = load_config("cpu", overrides=["loop.register_iters=17"], env={})
    refiner = PoseRefiner.from_config(cfg, registry=None)
    expected = {**tracker_args_from_config(cfg.tracking), "iters": 17}
    assert refiner.tracker_args == expected
