import numpy as np
import pytest
import torch
import torch.nn.functional as F

from posefuse_train import labels
from posefuse_train.camera_net import CameraNet
from posefuse_train.config import CameraNetConfig, PointNetConfig
from posefuse_train.data import load
from posefuse_train.keypoints import FLIP, NAMES, K
from posefuse_train.losses import heatmap_loss, heatmap_targets, regression_loss, segmentation_loss
from posefuse_train.train import (
    TrainCameraConfig,
    TrainPointConfig,
    augment,
    facing_loss,
    facing_target,
    normalize,
    select_points,
    to_input,
    train_point,
)


def test_regression_loss_is_scaled_weighted_huber():
    pred = torch.zeros(1, K, 3)
    target = torch.zeros(1, K, 3)
    target[0, 0, 0] = 0.052 * 0.5  # nose off by half its scale: Huber(0.5) = 0.125
    target[0, 1, 2] = 0.158 * 3.0  # shoulder off by 3 scales: Huber(3) = 2.5
    w = torch.zeros(1, K)
    w[0, 0], w[0, 1] = 1.0, 0.4
    got = regression_loss(pred, target, w).item()
    assert abs(got - (0.125 + 0.4 * 2.5) / K) < 1e-6


def test_segmentation_loss_weights_positives_and_skips_invisible():
    logits = torch.zeros(1, 2, K)
    lab = torch.zeros(1, 2, K)
    lab[0, 0, 0] = 1.0
    vis = torch.zeros(1, K)
    vis[0, 0] = 1.0
    got = segmentation_loss(logits, lab, vis, w_pos=10.0, w_neg=1.0).item()
    # ln 2 per entry; keypoint 0: (10 + 1)/2 points; others invisible; mean over K
    assert abs(got - (10 + 1) / 2 * np.log(2) / K) < 1e-6


def test_heatmap_targets_peak_at_the_keypoint_cell():
    kp = torch.tensor([[[20.0, 8.0], [100.0, 8.0]]])
    t, w = heatmap_targets(kp, torch.ones(1, 2), 64, 16, 1.0)
    assert t[0, 0].argmax().item() == 2 * 16 + 5  # (x, y) = (20, 8) px -> cell col 5, row 2
    assert t[0, 0].max().item() == 1.0
    assert w.tolist() == [[1.0, 0.0]] and t[0, 1].abs().sum() == 0  # outside the heatmap


def test_flip_augmentation_moves_keypoints_with_the_image():
    s = 32
    img = torch.zeros(1, 3, s, s)
    img[0, :, 10, 5] = 1.0  # pixel centre (5.5, 10.5)
    kp = torch.zeros(1, K, 2)
    kp[0, 1] = torch.tensor([5.5, 10.5])  # left shoulder at the dot
    vis = torch.zeros(1, K)
    vis[0, 1] = 1.0
    cfg = TrainCameraConfig(rotate_prob=0.0, scale_range=0.0, flip_prob=1.0)
    x, kp2, vis2 = augment(img, kp, vis, cfg, torch.Generator().manual_seed(0))
    j = x[0, 0].argmax().item()
    assert (j // s, j % s) == (10, s - 1 - 5)
    # the dot is now labelled as the right shoulder, at the mirrored position
    assert vis2[0, FLIP[1]] == 1.0 and vis2[0, 1] == 0.0
    np.testing.assert_allclose(kp2[0, FLIP[1]].numpy(), [s - 5.5, 10.5], atol=1e-5)


def test_rotation_augmentation_keeps_keypoints_on_the_content():
    s = 32
    img = torch.zeros(1, 3, s, s)
    img[0, :, 6:9, 20:23] = 1.0  # blob centred at (21.5, 7.5)
    kp = torch.full((1, K, 2), 16.0)
    kp[0, 0] = torch.tensor([21.5, 7.5])
    cfg = TrainCameraConfig(rotate_prob=1.0, rotate_deg=40.0, scale_range=0.2, flip_prob=0.0)
    x, kp2, _ = augment(img, kp, torch.ones(1, K), cfg, torch.Generator().manual_seed(3))
    m = x[0, 0]
    ys, xs = torch.meshgrid(torch.arange(s) + 0.5, torch.arange(s) + 0.5, indexing="ij")
    centre = torch.stack([(m * xs).sum() / m.sum(), (m * ys).sum() / m.sum()])
    assert torch.dist(centre, kp2[0, 0]) < 0.3


def test_point_selection_covers_small_sets_and_subsamples_large_ones():
    idx = select_points(torch.tensor([3, 10]), 6, 12, torch.Generator().manual_seed(0))
    assert sorted(idx[0, :3].tolist()) == [0, 1, 2] and (idx[0] < 3).all()
    assert len(set(idx[1].tolist())) == 6 and (idx[1] < 10).all()


def test_a_few_camera_steps_reduce_the_loss(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[0])
    torch.manual_seed(0)
    net = CameraNet(CameraNetConfig(backbone="resnet18-w16", deconv_channels=32))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    x = normalize(to_input(d["image"][:32], "cpu"), cfg)
    t, w = heatmap_targets(
        torch.from_numpy(d["kp2d"][:32]),
        torch.from_numpy(d["kp2d_visible"][:32]).float(),
        cfg.image_size,
        cfg.heatmap_size,
        1.0,
    )
    losses = []
    for _ in range(12):
        loss = heatmap_loss(net(x), t, w)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.85 * losses[0]


def test_point_training_reduces_the_loss(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[0])
    lab = labels.pseudo_labels(d, cfg, t_r=200.0)
    sm = (
        np.random.default_rng(0)
        .random((len(d["kp2d"]), K, cfg.heatmap_size, cfg.heatmap_size))
        .astype(np.float32)
    )
    small = PointNetConfig(
        in_features=3 + K,
        local_channels=(16, 32),
        global_channels=(64,),
        head_channels=(64,),
        seg_channels=(16,),
    )
    pcfg = TrainPointConfig(epochs=12, batch_size=32, lr=0.02, warmup_steps=2, rotate_deg=10.0)
    net = train_point(d, lab, sm, cfg, small, pcfg, log=lambda _: None)
    h = net.loss_history
    assert len(h) == 36 and np.mean(h[-5:]) < 0.6 * np.mean(h[:5])


def person(left_x: float, right_x: float, s: int = 64):
    """2D labels with the left shoulder and hip at `left_x`, the right ones at `right_x`."""
    kp = torch.full((1, K, 2), s / 2)
    vis = torch.ones(1, K)
    for name, x, y in (
        ("left_shoulder", left_x, 20.0),
        ("right_shoulder", right_x, 20.0),
        ("left_hip", left_x, 40.0),
        ("right_hip", right_x, 40.0),
    ):
        kp[0, NAMES.index(name)] = torch.tensor([x, y])
    return kp, vis


def test_the_facing_target_reads_front_and_back_from_left_and_right():
    # facing the camera, a person's left is on the image's right
    kp, vis = person(40.0, 24.0)
    assert facing_target(kp, vis, 64) == (torch.tensor([1.0]), torch.tensor([1.0]))
    kp, vis = person(24.0, 40.0)
    assert facing_target(kp, vis, 64) == (torch.tensor([0.0]), torch.tensor([1.0]))
    # side-on (within 3 % of the crop) or a hip not seen: unknown
    kp, vis = person(32.5, 32.0)  # shoulders and hips together 1 px apart
    assert facing_target(kp, vis, 64)[1].item() == 0.0
    kp, vis = person(40.0, 24.0)
    vis[0, NAMES.index("right_hip")] = 0.0
    assert facing_target(kp, vis, 64)[1].item() == 0.0


def test_a_flipped_crop_keeps_its_facing_target():
    kp, vis = person(44.0, 20.0)
    cfg = TrainCameraConfig(rotate_prob=0.0, scale_range=0.0, flip_prob=1.0)
    _, kp2, vis2 = augment(torch.zeros(1, 3, 64, 64), kp, vis, cfg, torch.Generator().manual_seed(0))
    # the labels did move: the crop's new left shoulder is the old right one, mirrored
    assert kp2[0, NAMES.index("left_shoulder"), 0] == pytest.approx(64 - 20.0)
    assert facing_target(kp2, vis2, 64) == facing_target(kp, vis, 64)


def test_the_facing_loss_counts_only_known_persons():
    logit = torch.tensor([2.0, -2.0, 5.0])
    front = torch.tensor([1.0, 1.0, 0.0])
    known = torch.tensor([1.0, 1.0, 0.0])
    want = (F.softplus(torch.tensor(-2.0)) + F.softplus(torch.tensor(2.0))) / 2
    assert torch.isclose(facing_loss(logit, front, known), want)
    assert facing_loss(logit, front, torch.zeros(3)).item() == 0.0


def test_a_camera_net_with_a_facing_head_exports_only_its_heatmaps():
    torch.manual_seed(0)
    net = CameraNet(CameraNetConfig(backbone="resnet18-w16", deconv_channels=16, facing_head=True)).eval()
    x = torch.randn(2, 3, 64, 64)
    with torch.no_grad():
        heatmaps, facing = net(x, with_facing=True)
        assert torch.equal(net(x), heatmaps) and facing.shape == (2,)
    plain = CameraNet(CameraNetConfig(backbone="resnet18-w16", deconv_channels=16))
    with pytest.raises(ValueError):
        plain(x, with_facing=True)


def test_camera_steps_with_the_facing_target_reduce_both_losses(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[0])
    torch.manual_seed(0)
    net = CameraNet(CameraNetConfig(backbone="resnet18-w16", deconv_channels=32, facing_head=True))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    x = normalize(to_input(d["image"][:32], "cpu"), cfg)
    kp, vis = torch.from_numpy(d["kp2d"][:32]), torch.from_numpy(d["kp2d_visible"][:32]).float()
    t, w = heatmap_targets(kp, vis, cfg.image_size, cfg.heatmap_size, 1.0)
    front, known = facing_target(kp, vis, cfg.image_size)
    assert known.sum() >= 4
    parts = []
    for _ in range(12):
        heatmaps, facing = net(x, with_facing=True)
        hm, fl = heatmap_loss(heatmaps, t, w), facing_loss(facing, front, known)
        opt.zero_grad()
        (hm + 1e-2 * fl).backward()
        opt.step()
        parts.append((hm.item(), fl.item()))
    assert parts[-1][0] < 0.85 * parts[0][0] and parts[-1][1] < 0.85 * parts[0][1]
