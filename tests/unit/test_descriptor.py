"""Place recognition descriptor: backbone weights, NetVLAD/GeM, determinism, weights files."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from cpslam.agent import descriptor as descriptor_module
from cpslam.agent.aggregation import GeM, NetVLAD, kmeans
from cpslam.agent.descriptor import (
    DEFAULT_LAYER,
    DescriptorExtractor,
    load_weights,
    procedural_images,
)
from cpslam.agent.efficientnet import (
    STAGES,
    EfficientNetLite0,
    load_efficientnet_lite0,
    normalize,
    shipped_weights_path,
)

SIZE = 96  # small images keep the untrained NetVLAD start-up well under a second


@pytest.fixture(scope="module")
def netvlad() -> DescriptorExtractor:
    return DescriptorExtractor("netvlad", clusters=8, image_size=SIZE, layer="stage5", seed=3)


@pytest.fixture(scope="module")
def gem() -> DescriptorExtractor:
    return DescriptorExtractor("gem", gem_p=3.0, image_size=SIZE, layer="head")


def test_shipped_weights_load_strictly_and_give_finite_features() -> None:
    state = torch.load(shipped_weights_path(), map_location="cpu", weights_only=True)
    model = EfficientNetLite0()
    missing, unexpected = model.load_state_dict(state, strict=True)
    assert not missing and not unexpected
    model.eval()
    x = normalize(torch.rand(1, 3, 64, 64) * 255)
    with torch.inference_mode():
        for layer, (channels, stride) in STAGES.items():
            f = model.features(x, layer)
            assert f.shape == (1, channels, 64 // stride, 64 // stride)
            assert torch.isfinite(f).all()


def test_backbone_classifies_a_natural_image() -> None:
    # Validates architecture, SAME padding and the [-1, 1] input scaling together: matplotlib
    # ships a photograph of Grace Hopper in navy uniform (ImageNet class 652, military uniform).
    mpl_data = pytest.importorskip("matplotlib").get_data_path()
    photo = Path(mpl_data) / "sample_data" / "grace_hopper.jpg"
    if not photo.is_file():
        pytest.skip(f"sample photograph not found at {photo}")
    rgb = cv2.cvtColor(cv2.imread(str(photo)), cv2.COLOR_BGR2RGB)
    h, w = rgb.shape[:2]
    s = min(h, w)
    rgb = rgb[(h - s) // 2 : (h - s) // 2 + s, (w - s) // 2 : (w - s) // 2 + s]
    rgb = cv2.resize(rgb, (224, 224), interpolation=cv2.INTER_AREA)
    x = normalize(torch.from_numpy(rgb).permute(2, 0, 1)[None].float())
    with torch.inference_mode():
        probs = load_efficientnet_lite0()(x).softmax(dim=1)[0]
    assert int(probs.argmax()) == 652
    assert float(probs.max()) > 0.3


def test_missing_backbone_file_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nothing.pth"):
        load_efficientnet_lite0(tmp_path / "nothing.pth")


@pytest.mark.parametrize("which", ["netvlad", "gem"])
def test_descriptor_unit_norm_dim_and_deterministic(which: str, request) -> None:
    extractor: DescriptorExtractor = request.getfixturevalue(which)
    images = procedural_images(3, 120, seed=11)
    a = extractor.compute_batch(list(images))
    b = extractor.compute_batch(list(images))
    assert a.dtype == np.float32 and a.shape == (3, extractor.dim)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(extractor.compute(images[1]), a[1], atol=1e-6)
    expected_dim = 8 * STAGES["stage5"][0] if which == "netvlad" else STAGES["head"][0]
    assert extractor.dim == expected_dim


def test_same_seed_same_centres_other_seed_other_centres(monkeypatch) -> None:
    def centres(seed: int) -> torch.Tensor:
        # An empty cache forces the k-means to run again rather than reuse the first result.
        monkeypatch.setattr(descriptor_module, "_INIT_CACHE", {})
        monkeypatch.setattr(descriptor_module, "INIT_IMAGES", 16)  # fast; same code path
        ex = DescriptorExtractor("netvlad", clusters=8, image_size=64, layer="stage6", seed=seed)
        return ex.pool.centroids.clone()

    first, again, other = centres(5), centres(5), centres(6)
    assert torch.equal(first, again)
    assert not torch.allclose(first, other)


@pytest.mark.parametrize("which", ["netvlad", "gem"])
def test_shifted_brightened_view_is_closer_than_another_scene(which: str, request) -> None:
    extractor: DescriptorExtractor = request.getfixturevalue(which)
    scene_a, scene_b = procedural_images(2, 240, seed=21)
    view = np.clip(scene_a[12:, 16:].astype(np.float32) * 1.15 + 10, 0, 255).astype(np.uint8)
    d = extractor.compute_batch([scene_a[:-12, :-16], view, scene_b])
    assert d[0] @ d[1] > d[0] @ d[2] + 0.05


@pytest.mark.parametrize("suffix", [".npz", ".pt"])
def test_weights_round_trip(netvlad: DescriptorExtractor, tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"netvlad{suffix}"
    if suffix == ".npz":
        netvlad.save_weights(path)
    else:
        torch.save(
            {
                "centroids": netvlad.pool.centroids,
                "conv.weight": netvlad.pool.conv_weight[..., None, None],
                "conv.bias": netvlad.pool.conv_bias,
            },
            path,
        )
    loaded = DescriptorExtractor("netvlad", image_size=SIZE, layer="stage5", weights=path)
    images = list(procedural_images(2, 100, seed=4))
    assert loaded.dim == netvlad.dim
    np.testing.assert_allclose(
        loaded.compute_batch(images), netvlad.compute_batch(images), atol=1e-5
    )


def test_gem_weights_with_projection(gem: DescriptorExtractor, tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    path = tmp_path / "gem.npz"
    np.savez(
        path,
        p=np.array(2.0),
        **{"pca.weight": rng.normal(size=(64, 1280)), "pca.bias": np.zeros(64)},
    )
    loaded = DescriptorExtractor("gem", image_size=SIZE, layer="head", weights=path)
    d = loaded.compute(procedural_images(1, 100, seed=1)[0])
    assert loaded.dim == 64 and d.shape == (64,)
    assert loaded.pool.p == 2.0
    assert abs(np.linalg.norm(d) - 1) < 1e-5


def test_weights_errors_name_file_and_key(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="absent.npz"):
        DescriptorExtractor("netvlad", weights=tmp_path / "absent.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, centroids=np.zeros((16, 100)))
    with pytest.raises(ValueError, match=r"bad\.npz.*'centroids'.*\[K, 112\]"):
        load_weights(bad, "netvlad", "stage5")
    np.savez(bad, centroids=np.zeros((16, 112)), **{"conv.bias": np.zeros(3)})
    with pytest.raises(ValueError, match=r"bad\.npz.*'conv\.bias'.*\[16\]"):
        load_weights(bad, "netvlad", "stage5")
    np.savez(bad, centroids=np.zeros((16, 112)), extra=np.zeros(2))
    with pytest.raises(ValueError, match=r"bad\.npz.*unknown keys \['extra'\]"):
        load_weights(bad, "netvlad", "stage5")
    np.savez(bad, centroids=np.zeros((4, 80)), layer=np.array("stage4"))
    with pytest.raises(ValueError, match=r"'layer'.*'stage4', but layer 'stage5'"):
        load_weights(bad, "netvlad", "stage5")
    np.savez(bad, p=np.array(3.0), layer=np.array("stage9"))
    with pytest.raises(ValueError, match=r"'layer'.*'stage9' is not one of"):
        load_weights(bad, "gem")
    np.savez(bad, p=np.array(-1.0))
    with pytest.raises(ValueError, match=r"'p'.*positive scalar"):
        load_weights(bad, "gem")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="garbage.pt"):
        load_weights(garbage, "gem")


def test_weights_file_names_the_layer(netvlad: DescriptorExtractor, tmp_path: Path) -> None:
    path = netvlad.save_weights(tmp_path / "stage5.npz")
    params, layer = load_weights(path, "netvlad")
    assert layer == "stage5" and tuple(params["centroids"].shape) == (8, 112)
    loaded = DescriptorExtractor("netvlad", image_size=SIZE, weights=path)
    assert loaded.layer == "stage5" and loaded.dim == netvlad.dim


def test_defaults_are_the_measured_choice() -> None:
    from cpslam.common.config import load_config

    ex = DescriptorExtractor(image_size=64)
    assert (ex.aggregation, ex.layer) == ("netvlad", DEFAULT_LAYER)
    assert ex.dim == 8 * STAGES[DEFAULT_LAYER][0]
    # The config's defaults build the same extractor.
    cfg = load_config("cpu").place_recognition
    from_cfg = DescriptorExtractor.from_config(cfg.model_copy(update={"image_size": 64}))
    assert (from_cfg.aggregation, from_cfg.layer, from_cfg.dim) == ("netvlad", "stage6", ex.dim)


def test_long_descriptors_are_sketched_and_the_sketch_round_trips(tmp_path: Path) -> None:
    ex = DescriptorExtractor("netvlad", clusters=8, image_size=64, layer="head", max_dim=512)
    images = list(procedural_images(2, 64, seed=2))
    d = ex.compute_batch(images)
    assert ex.dim == 512 and d.shape == (2, 512)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    path = ex.save_weights(tmp_path / "sketched.npz")
    loaded = DescriptorExtractor("netvlad", image_size=64, weights=path, seed=99)
    assert loaded.dim == 512
    np.testing.assert_allclose(loaded.compute_batch(images), d, atol=1e-5)


def test_count_sketch_preserves_cosine_roughly() -> None:
    rng = np.random.default_rng(0)
    x = torch.from_numpy(rng.normal(size=(20, 8192))).float()
    x[10:] = x[:10] + 0.8 * torch.from_numpy(rng.normal(size=(10, 8192))).float()
    bucket, sign = descriptor_module._count_sketch(8192, 1024, seed=0)
    y = torch.zeros(20, 1024).index_add_(1, bucket, x * sign)
    cos = torch.nn.functional.cosine_similarity
    err = (cos(x[:10], x[10:]) - cos(y[:10], y[10:])).abs()
    assert err.max() < 0.1


def test_from_config() -> None:
    from cpslam.common.config.collab import PlaceRecognitionConfig

    cfg = PlaceRecognitionConfig(aggregation="gem", gem_p=2.0, image_size=64)
    ex = DescriptorExtractor.from_config(cfg, device="cpu")
    assert ex.aggregation == "gem" and ex.pool.p == 2.0 and ex.image_size == 64


def test_bad_inputs_raise() -> None:
    with pytest.raises(ValueError, match="aggregation"):
        DescriptorExtractor("vlad")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="layer"):
        DescriptorExtractor("gem", layer="stage9")
    ex = DescriptorExtractor("gem", image_size=64)
    with pytest.raises(ValueError, match="image 0: expected RGB uint8"):
        ex.compute(np.zeros((32, 32), np.uint8))
    assert ex.compute_batch([]).shape == (0, ex.dim)


def test_kmeans_finds_separated_clusters_deterministically() -> None:
    gen = torch.Generator().manual_seed(0)
    truth = torch.tensor([[0.0, 0.0], [5.0, 5.0], [-5.0, 5.0]])
    x = torch.cat([c + 0.1 * torch.randn(50, 2, generator=gen) for c in truth])
    c1, c2 = kmeans(x, 3, seed=1), kmeans(x, 3, seed=1)
    assert torch.equal(c1, c2)
    nearest = torch.cdist(truth, c1).min(dim=1).values
    assert (nearest < 0.1).all()


def test_pooling_layers() -> None:
    feat = torch.rand(2, 4, 3, 3) + 0.1
    np.testing.assert_allclose(
        GeM(1.0)(feat), torch.nn.functional.normalize(feat.mean(dim=(2, 3)), dim=1), atol=1e-6
    )
    vlad = NetVLAD(torch.nn.functional.normalize(torch.randn(5, 4), dim=1), alpha=10.0)
    out = vlad(feat)
    assert out.shape == (2, 20) and vlad.dim == 20
    np.testing.assert_allclose(out.norm(dim=1), 1.0, atol=1e-5)
    with pytest.raises(ValueError, match="conv_weight/conv_bias or alpha"):
        NetVLAD(torch.randn(5, 4))
