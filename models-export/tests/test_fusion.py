import json
import math

import numpy as np
import pytest
import torch
from conftest import GOLDEN

from posefuse_train import fusion, labels


def test_kernel_sums_to_one_with_the_expected_ratio():
    g = fusion.gaussian_kernel(7, 3.0)
    assert g.shape == (7, 7)
    assert abs(g.sum() - 1.0) < 1e-6
    assert g.max() == g[3, 3]
    assert abs(g[3, 4] / g[3, 3] - math.exp(-1 / 18)) < 1e-6


def test_smoothing_a_delta_gives_the_kernel_and_edges_lose_mass():
    hm = torch.zeros(1, 1, 9, 9)
    hm[0, 0, 4, 4] = 1.0
    s = fusion.smooth_heatmaps(hm, 7, 3.0)[0, 0].numpy()
    np.testing.assert_allclose(s[1:8, 1:8], fusion.gaussian_kernel(7, 3.0), atol=1e-7)
    corner = torch.zeros(1, 1, 9, 9)
    corner[0, 0, 0, 0] = 1.0
    inside = fusion.gaussian_kernel(7, 3.0)[3:, 3:].sum()
    assert abs(fusion.smooth_heatmaps(corner, 7, 3.0).sum().item() - inside) < 1e-6


def test_cell_index_rounds_and_clamps_like_the_server():
    x = np.array([2.0, 1.99, 63.9, -10.0], np.float32)
    np.testing.assert_array_equal(fusion.cell_index(x, 16, 64), [1, 0, 15, 0])
    np.testing.assert_array_equal(fusion.cell_index(torch.from_numpy(x), 16, 64).numpy(), [1, 0, 15, 0])
    hm = torch.arange(2 * 4 * 4, dtype=torch.float32).view(1, 2, 4, 4)
    f = fusion.sample_features(hm, torch.tensor([[[9.0, 4.0], [float("nan"), 1.0]]]), 16)
    # x = 9 -> 2.25 + 0.5 -> col 2; y = 4 -> 1.5 -> row 1
    np.testing.assert_array_equal(f[0].numpy(), [[6.0, 22.0], [0.0, 0.0]])


def test_bilinear_sampling_blends_the_four_cells_around_a_point():
    hm = torch.arange(16, dtype=torch.float32).view(1, 1, 4, 4)
    uv = torch.tensor([[[6.0, 2.0], [4.0, 4.0], [-3.0, 15.0], [float("nan"), 1.0], [13.0, 9.0]]])
    # the same hand-computed values as the server's unit test (crates/core/src/pipeline/fusion.rs)
    f = fusion.sample_features(hm, uv, 16, "bilinear")[0, :, 0]
    np.testing.assert_array_equal(f.numpy(), [3.5, 5.0, 12.0, 0.0, 12.0])
    with pytest.raises(ValueError, match="nearest or bilinear"):
        fusion.sample_features(hm, uv, 16, "bicubic")


def test_the_manifest_names_the_sampling_only_when_it_is_not_the_nearest_cell():
    from posefuse_train.config import PipelineConfig

    assert "sampling" not in PipelineConfig().to_dict()
    d = PipelineConfig(sampling="bilinear").to_dict()
    assert d["sampling"] == "bilinear" and PipelineConfig.from_dict(d).sampling == "bilinear"


def test_decode_finds_the_peak_with_a_quarter_shift():
    hm = np.zeros((1, 2, 4, 4), np.float32)
    hm[0, 0, 1, 2], hm[0, 0, 1, 3] = 0.9, 0.5  # right neighbour larger
    hm[0, 1, 3, 0] = 0.7  # corner: no shift
    uv, score = fusion.decode_heatmaps(hm, 16)
    np.testing.assert_allclose(uv[0], [[(2 + 0.25) * 4, 4.0], [0.0, 12.0]])
    np.testing.assert_allclose(score[0], [0.9, 0.7])


def rows(x, width):
    """JSON rows where null (a whole row or one value) stands for NaN."""
    return [[np.nan] * width if p is None else [np.nan if v is None else v for v in p] for p in x]


def _golden(name):
    path = GOLDEN / name
    if not path.exists():
        pytest.fail(f"{path} is missing: it is written from the Rust pipeline and pins the Python copy")
    return json.loads(path.read_text())


def test_fusion_matches_the_server_golden_vectors():
    g = _golden("fusion.json")
    k, h, w, s = g["k"], g["h"], g["w"], g["image_size"]
    np.testing.assert_allclose(
        fusion.gaussian_kernel(g["kernel_size"], g["sigma"]).ravel(), g["kernel"], rtol=0, atol=1e-7
    )
    hm = torch.tensor(g["heatmaps"], dtype=torch.float32).view(1, k, h, w)
    sm = fusion.smooth_heatmaps(hm, g["kernel_size"], g["sigma"])
    np.testing.assert_allclose(sm.numpy().ravel(), g["smoothed"], rtol=0, atol=1e-6)
    uv = torch.tensor(rows(g["uv"], 2), dtype=torch.float32)
    feats = fusion.sample_features(
        torch.tensor(g["smoothed"], dtype=torch.float32).view(1, k, h, w), uv[None], s
    )
    np.testing.assert_allclose(feats[0].numpy().ravel(), g["features"], rtol=0, atol=0)
    bilinear = fusion.sample_features(
        torch.tensor(g["smoothed"], dtype=torch.float32).view(1, k, h, w), uv[None], s, "bilinear"
    )
    np.testing.assert_allclose(bilinear[0].numpy().ravel(), g["bilinear_features"], rtol=0, atol=1e-6)


def test_lift_matches_the_server_golden_vectors():
    g = _golden("lift.json")

    def arr(x, width):
        return np.array(rows(x, width), np.float32)[None]

    kp, uv, xyz = arr(g["kp_uv"], 2), arr(g["points_uv"], 2), arr(g["points_xyz"], 3)
    out = labels.lift(kp, uv, xyz, None, g["image_size"], g["temperature"])
    np.testing.assert_allclose(out, arr(g["lifted"], 3), rtol=1e-5, atol=1e-6)
    r = labels.reliability(kp, uv, None, g["image_size"], g["t_r"])
    np.testing.assert_allclose(r[0], g["reliability"], rtol=1e-5, atol=1e-7)
