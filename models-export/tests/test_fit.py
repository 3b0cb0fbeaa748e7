"""The training loop: a run's length is fixed by its configuration, so the same seed gives the same
weights; the wall-clock budget only applies when asked for."""

import numpy as np
import pytest
import torch

from posefuse_train import labels, train
from posefuse_train.config import CameraNetConfig, PointNetConfig
from posefuse_train.data import load
from posefuse_train.keypoints import K

SMALL_POINT = dict(local_channels=(16,), global_channels=(32,), head_channels=(32,), seg_channels=(16,))


def tiny_camera(d, cfg, **over):
    net_cfg = CameraNetConfig(backbone="resnet18-w16", deconv_channels=16)
    tcfg = train.TrainCameraConfig(epochs=2, batch_size=32, **over)
    return train.train_camera(d, cfg, net_cfg, tcfg, log=lambda _: None)


def tiny_point(d, cfg, seed=0):
    lab = labels.pseudo_labels(d, cfg, t_r=200.0)
    sm = np.random.default_rng(0).random((len(d["kp2d"]), K, cfg.heatmap_size, cfg.heatmap_size))
    pcfg = train.TrainPointConfig(epochs=2, batch_size=32, warmup_steps=2, seed=seed)
    net_cfg = PointNetConfig(in_features=3 + K, **SMALL_POINT)
    return train.train_point(d, lab, sm.astype(np.float32), cfg, net_cfg, pcfg, log=lambda _: None)


def same_weights(a, b) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_the_same_seed_trains_the_same_weights(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[0])
    cam_a, cam_b = tiny_camera(d, cfg), tiny_camera(d, cfg)
    assert len(cam_a.loss_history) == 2 * (96 // 32)
    assert cam_a.loss_history == cam_b.loss_history and same_weights(cam_a, cam_b)
    pt_a, pt_b = tiny_point(d, cfg), tiny_point(d, cfg)
    assert pt_a.loss_history == pt_b.loss_history and same_weights(pt_a, pt_b)
    # ...and the comparison can tell: another seed gives other weights
    assert not same_weights(pt_a, tiny_point(d, cfg, seed=1))
    assert not same_weights(cam_a, tiny_camera(d, cfg, seed=1))


class SlowClock:
    """A clock on which every reading is 100 s after the previous one: a very slow machine."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        self.t += 100.0
        return self.t


@pytest.mark.parametrize("budget_s", [0.0, 250.0])
def test_the_wall_clock_budget_is_opt_in(budget_s):
    net = torch.nn.Linear(2, 1)
    opt = torch.optim.SGD(net.parameters(), lr=0.1)
    lrs = []

    def lr_at(step, total):
        lrs.append((step, total))
        return 0.1 * (1 - step / total)

    x = torch.ones(4, 2)
    history = train.fit(
        net,
        opt,
        lambda _: net(x).square().mean(),
        lr_at,
        60,
        time_budget_s=budget_s,
        min_steps=10,
        clock=SlowClock(),
    )
    # without a budget the slow clock changes nothing; with one the run stops after a few steps
    # (never fewer than min_steps), and the schedule is compressed to end with the run
    n = len(history)
    assert n == 60 if budget_s == 0 else 10 <= n < 20
    assert lrs[-1] == (n - 1, n) and not net.training
