"""Training data read lazily: the index, the sampler's order (the old in-memory order when the set
fits, shuffled across shards when it does not), the loader's bound on shards in memory, and
training on shards equal to training on the same arrays in memory."""

import dataclasses

import numpy as np
import pytest
import torch

from posefuse_train import labels as labels_mod
from posefuse_train import train
from posefuse_train.config import CameraNetConfig, PointNetConfig
from posefuse_train.data import load
from posefuse_train.keypoints import K
from posefuse_train.shards import IndexSampler, ShardLoader, ShardSet, window_shards


def old_batches(rng, indices, batch_size):
    """The trainer's order before it streamed (its `train.batches`): a fresh permutation per
    epoch, carried over into the next."""
    order = np.empty(0, np.int64)
    while True:
        if len(order) < batch_size:
            order = np.concatenate([order, rng.permutation(indices)])
        yield order[:batch_size]
        order = order[batch_size:]


def test_the_index_reads_counts_and_the_widest_person_without_the_arrays(synthetic_sets):
    s = ShardSet(synthetic_sets[0])
    d, cfg, _ = load(synthetic_sets[0])
    assert s.counts.tolist() == [40, 40, 16] and len(s) == 96
    assert s.points_width == d["points_xyz"].shape[1] == int(d["points_count"].max())
    assert s.cfg == cfg
    assert s.shard_of(np.array([0, 39, 40, 95])).tolist() == [0, 0, 1, 2]
    # every shard is padded to the same point width, and a shard's rows are the set's rows
    got = s.read(2, ["points_xyz", "kp2d"])
    assert got["points_xyz"].shape[1] == s.points_width
    np.testing.assert_array_equal(got["points_xyz"], d["points_xyz"][80:96])
    assert s.shard_bytes(["image"]) >= 40 * 32 * 32 * 3


def test_a_set_that_fits_is_drawn_in_the_old_in_memory_order(synthetic_sets):
    s = ShardSet(synthetic_sets[0])
    usable = np.ones(len(s), bool)
    usable[[3, 50, 90]] = False
    sampler = IndexSampler(s, usable, 32, window=s.num_shards, rng=np.random.default_rng(7))
    old = old_batches(np.random.default_rng(7), np.flatnonzero(usable), 32)
    for _ in range(10):
        np.testing.assert_array_equal(sampler.next(), next(old))


def test_a_set_that_does_not_fit_is_shuffled_across_shards_one_window_at_a_time(synthetic_sets):
    s = ShardSet(synthetic_sets[0])
    usable = np.ones(len(s), bool)
    sampler = IndexSampler(s, usable, 8, window=1, rng=np.random.default_rng(0))
    epochs = [np.concatenate([sampler.next() for _ in range(12)]) for _ in range(3)]
    for e in epochs:
        assert sorted(e.tolist()) == list(range(96))  # every sample once per epoch
    # the shards come in a different order in different epochs...
    firsts = [int(s.shard_of(e[:1])[0]) for e in epochs]
    orders = [tuple(dict.fromkeys(s.shard_of(e).tolist())) for e in epochs]
    assert len(set(orders)) > 1, (firsts, orders)
    # ...and a batch draws from at most two shards (the end of one window, the start of the next)
    for e in epochs:
        for b in e.reshape(-1, 8):
            assert len(set(s.shard_of(b).tolist())) <= 2


def test_the_sampler_resumes_from_its_state(synthetic_sets):
    s = ShardSet(synthetic_sets[0])
    a = IndexSampler(s, np.ones(96, bool), 24, window=1, rng=np.random.default_rng(3))
    for _ in range(5):
        a.next()
    state = a.state_dict()
    b = IndexSampler(s, np.ones(96, bool), 24, window=1, rng=np.random.default_rng(99))
    b.load_state_dict(state)
    for _ in range(10):
        np.testing.assert_array_equal(a.next(), b.next())


def test_the_loader_keeps_at_most_its_capacity_of_shards_and_gathers_the_right_rows(synthetic_sets):
    s = ShardSet(synthetic_sets[0])
    d, _, _ = load(synthetic_sets[0])
    loader = ShardLoader(s, ["kp2d", "points_xyz"], capacity=1)
    try:
        sampler = IndexSampler(s, np.ones(96, bool), 8, window=1, rng=np.random.default_rng(0))
        for _ in range(30):
            idx = sampler.next()
            loader.prefetch(sampler.upcoming_shards())
            got = loader.gather(idx)
            np.testing.assert_array_equal(got["kp2d"], d["kp2d"][idx])
            np.testing.assert_array_equal(got["points_xyz"], d["points_xyz"][idx])
            assert len(loader.cache) <= 1
    finally:
        loader.close()
    assert loader.loads > s.num_shards  # shards were dropped and read again


def test_the_window_is_a_third_of_the_memory_budget(synthetic_sets):
    s = ShardSet(synthetic_sets[0])
    per = s.shard_bytes(["image"])
    assert window_shards(s, ["image"], 3 * per / 1e6) == 1
    assert window_shards(s, ["image"], 6 * per / 1e6) == 2
    assert window_shards(s, ["image"], 1e-6) == 1
    assert window_shards(s, ["image"], 1e6) == s.num_shards


def same_weights(a, b) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_training_on_shards_that_fit_equals_training_on_the_arrays(synthetic_sets):
    d, cfg, _ = load(synthetic_sets[0])
    shards = ShardSet(synthetic_sets[0])
    net_cfg = CameraNetConfig(backbone="resnet18-w16", deconv_channels=16)
    tcfg = train.TrainCameraConfig(steps=4, batch_size=32)
    quiet = dict(log=lambda _: None)
    cam_mem = train.train_camera(d, cfg, net_cfg, tcfg, **quiet)
    cam_shards = train.train_camera(shards, cfg, net_cfg, tcfg, **quiet)
    assert cam_mem.loss_history == cam_shards.loss_history and same_weights(cam_mem, cam_shards)

    lab = labels_mod.pseudo_labels(d, cfg, t_r=200.0)
    streamed = train.stream_labels(shards, cfg, 200.0, train.TrainPointConfig(depth_correction=False))
    for k in ("kp3d", "weight", "visible"):
        np.testing.assert_array_equal(lab[k], streamed[k])
    # labels for occluded keypoints read the camera columns from the shards as well
    # (at the config's segmentation radius: a point that near an occluded label is the occluder's)
    rays = dict(occluded_weight=0.5, snap_to_rays=True)
    occ = labels_mod.pseudo_labels(d, cfg, 200.0, True, occluded_radius=0.02, **rays)
    point = train.TrainPointConfig(depth_correction=True, seg_radius=0.02, **rays)
    occ_streamed = train.stream_labels(shards, cfg, 200.0, point)
    at_default = labels_mod.pseudo_labels(d, cfg, 200.0, True, **rays)
    assert (occ["weight"] == 0.5).sum() > (at_default["weight"] == 0.5).sum()
    for k in ("kp3d", "weight", "visible"):
        np.testing.assert_array_equal(occ[k], occ_streamed[k])
    # the fusion net: heatmaps precomputed over the arrays, or computed per shard as it is read
    from posefuse_train.fusion import smoothed

    sm = smoothed(train.predict_heatmaps(cam_mem, d["image"], cfg, progress=False), cfg)
    pcfg = train.TrainPointConfig(steps=4, batch_size=32, warmup_steps=2)
    pnet = PointNetConfig(
        in_features=3 + K,
        local_channels=(16,),
        global_channels=(32,),
        head_channels=(32,),
        seg_channels=(16,),
    )
    pt_mem = train.train_point(d, lab, sm, cfg, pnet, pcfg, **quiet)
    pt_shards = train.train_point(shards, streamed, cam_shards, cfg, pnet, pcfg, **quiet)
    np.testing.assert_allclose(pt_mem.loss_history, pt_shards.loss_history, rtol=1e-5)
    # without labels given, the run makes them as its config says, occluded ones included
    lidar = dataclasses.replace(pnet, in_features=3)
    occ_cfg = dataclasses.replace(
        pcfg, fusion=False, depth_correction=True, occluded_weight=0.5, snap_to_rays=True, seg_radius=0.02
    )
    made = train.train_point(shards, None, None, cfg, lidar, occ_cfg, **quiet)
    given = train.train_point(shards, occ_streamed, None, cfg, lidar, occ_cfg, **quiet)
    assert made.loss_history == given.loss_history
    for plain in ({"occluded_weight": 0.0}, {"snap_to_rays": False}):
        other = dataclasses.replace(occ_cfg, **plain)
        without = train.train_point(shards, None, None, cfg, lidar, other, **quiet)
        assert without.loss_history != made.loss_history, plain
    # a second round's labels: the first round's nets' mean answer (the fusion net on the camera's
    # heatmaps) shard by shard, as over the arrays in memory
    assert shards.num_shards > 1
    second = dataclasses.replace(occ_cfg, self_train=0.25)
    streamed2 = train.next_round_labels(shards, occ_streamed, (pt_mem, made), cam_mem, cfg, second)
    xyz, uv = d["serve_xyz"], d["serve_uv"]
    answer = train.predict_points(pt_mem, xyz, uv, sm, cfg) + train.predict_points(made, xyz, uv, None, cfg)
    in_memory = labels_mod.relabelled(occ_streamed, d, answer / 2, 0.25)
    given = train.next_round_labels(d, occ_streamed, (pt_mem, made), sm, cfg, second)  # heatmaps given
    for k in ("kp3d", "weight", "visible"):
        np.testing.assert_allclose(streamed2[k], in_memory[k], atol=1e-5)
        np.testing.assert_array_equal(given[k], in_memory[k])
    assert (streamed2["weight"] == 0.25).sum() > (occ_streamed["weight"] == 0.5).sum()


@pytest.mark.parametrize("memory_mb", [0.0, 0.05])
def test_a_run_trains_with_the_set_in_memory_or_one_shard_at_a_time(synthetic_sets, memory_mb):
    shards = ShardSet(synthetic_sets[0])
    d, cfg, _ = load(synthetic_sets[0])
    opts = train.RunOptions(memory_mb=memory_mb)
    tcfg = train.TrainCameraConfig(steps=6, batch_size=16)
    net = train.train_camera(
        shards, cfg, CameraNetConfig(deconv_channels=16), tcfg, log=lambda _: None, opts=opts
    )
    assert len(net.loss_history) == 6 and all(np.isfinite(net.loss_history))


def test_bf16_autocast_and_channels_last_train_on_the_cpu(synthetic_sets):
    """The CUDA options' code path (bf16 autocast, channels-last camera input), run on the CPU:
    finite losses, float32 weights, the same samples as without them."""
    shards = ShardSet(synthetic_sets[0])
    d, cfg, _ = load(synthetic_sets[0])
    tcfg = train.TrainCameraConfig(steps=3, batch_size=16)
    plain = train.train_camera(shards, cfg, CameraNetConfig(deconv_channels=16), tcfg, log=lambda _: None)
    opts = train.RunOptions(amp=True, channels_last=True)
    fast = train.train_camera(
        shards, cfg, CameraNetConfig(deconv_channels=16), tcfg, log=lambda _: None, opts=opts
    )
    assert len(fast.loss_history) == 3 and all(np.isfinite(fast.loss_history))
    assert all(p.dtype == torch.float32 for p in fast.parameters())
    # bf16 rounds the forward pass: close to the float32 run's first loss, not equal
    assert fast.loss_history[0] == pytest.approx(plain.loss_history[0], rel=0.05)
    assert fast.loss_history[0] != plain.loss_history[0]
    lab = labels_mod.pseudo_labels(d, cfg, t_r=200.0)
    pnet = PointNetConfig(
        in_features=3, local_channels=(16,), global_channels=(32,), head_channels=(32,), seg_channels=(16,)
    )
    pcfg = train.TrainPointConfig(fusion=False, steps=3, batch_size=16, warmup_steps=1)
    pt = train.train_point(
        shards, lab, None, cfg, pnet, pcfg, log=lambda _: None, opts=train.RunOptions(amp=True)
    )
    assert all(np.isfinite(pt.loss_history))
