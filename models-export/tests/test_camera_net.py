import pytest
import torch
import torch.nn.functional as F
from torch import nn

from posefuse_train.camera_net import (
    CameraNet,
    FlipTest,
    check_heatmap_size,
    deconv_layers_for,
    predicted_heatmap_size,
)
from posefuse_train.config import CameraNetConfig
from posefuse_train.keypoints import FLIP, K


@pytest.mark.parametrize("upsample", ["deconv", "shuffle"])
@pytest.mark.parametrize(
    ("layers", "shuffle", "side"),
    [(3, 1, 16), (4, 1, 32), (3, 2, 32), (2, 2, 16)],
)
def test_the_heatmap_side_is_what_the_config_says(layers, shuffle, side, upsample):
    cfg = CameraNetConfig(deconv_channels=8, deconv_layers=layers, final_shuffle=shuffle, upsample=upsample)
    assert predicted_heatmap_size(64, cfg) == side
    assert deconv_layers_for(64, side, shuffle) == layers
    with torch.no_grad():
        assert CameraNet(cfg).eval()(torch.zeros(1, 3, 64, 64)).shape == (1, K, side, side)


def test_each_upsampling_stage_is_the_kind_asked_for():
    """ "shuffle" stages hold no transposed convolution, and their BatchNorm sits before the pixel
    shuffle, on the convolution's own channels, so that export folds it into the convolution."""
    deconv = CameraNet(CameraNetConfig(deconv_channels=8, deconv_layers=2))
    shuffle = CameraNet(CameraNetConfig(deconv_channels=8, deconv_layers=2, upsample="shuffle"))
    assert [type(m) for m in deconv.deconv] == [nn.ConvTranspose2d, nn.BatchNorm2d, nn.ReLU] * 2
    assert [type(m) for m in shuffle.deconv] == [nn.Conv2d, nn.BatchNorm2d, nn.ReLU, nn.PixelShuffle] * 2
    assert shuffle.deconv[0].out_channels == shuffle.deconv[1].num_features == 4 * 8
    with pytest.raises(ValueError, match="upsample must be one of"):
        CameraNetConfig(upsample="bilinear")


def test_sub_cells_land_where_pixel_shuffle_puts_them():
    """Channel k·4 + 2·dy + dx of the last conv is sub-cell (dy, dx) of keypoint k's cells."""
    net = CameraNet(CameraNetConfig(deconv_channels=8, final_shuffle=2)).eval()
    with torch.no_grad():
        net.final.weight.zero_()
        net.final.bias.copy_(torch.arange(4 * K, dtype=torch.float32) - 100.0)
        logits = net.logits(torch.zeros(1, 3, 64, 64))[0]
    for k in (0, 5, K - 1):
        for dy in (0, 1):
            for dx in (0, 1):
                want = k * 4 + 2 * dy + dx - 100.0
                assert torch.all(logits[k, dy::2, dx::2] == want)


def test_a_heatmap_side_no_net_predicts_is_refused():
    with pytest.raises(ValueError, match="must be image_size 64"):
        deconv_layers_for(64, 24)
    with pytest.raises(ValueError, match="predicts for 64 px crops"):
        check_heatmap_size(64, 32, CameraNetConfig())
    check_heatmap_size(64, 32, CameraNetConfig(final_shuffle=2))


def test_training_refuses_heatmaps_the_net_cannot_predict():
    from posefuse_train.config import PipelineConfig
    from posefuse_train.train import TrainCameraConfig, train_camera

    cfg = PipelineConfig.with_image_size(64)
    cfg.heatmap_size = 32
    with pytest.raises(ValueError, match="final_shuffle 1"):
        train_camera(None, cfg, CameraNetConfig(), TrainCameraConfig())


class MirrorExact(nn.Module):
    """Heatmap cell j is the mean of the pixels around j·S/W (the decode's convention), channel k
    weighted 1 + k: its answer to a mirrored crop is exactly its answer mirrored, but left and right
    channels differ."""

    stride = 4

    def forward(self, x):
        s = self.stride
        cells = F.avg_pool2d(F.pad(x[:, :1], (s // 2, 0, s // 2, 0)), s)
        return cells * torch.arange(1, K + 1, dtype=x.dtype).view(1, K, 1, 1)


def test_the_flip_test_puts_the_mirror_answer_back_on_the_cells_it_came_from():
    torch.manual_seed(0)
    x = torch.rand(3, 3, 32, 32)
    net = MirrorExact()
    plain = net(x)
    got = FlipTest(net)(x)
    # off column 0, each channel is the mean of its own and its mirror partner's weight
    w = (torch.arange(1, K + 1) + torch.tensor(FLIP) + 1).float().view(1, K, 1, 1) / 2
    torch.testing.assert_close(got[..., 1:], (plain / torch.arange(1, K + 1).view(1, K, 1, 1) * w)[..., 1:])
    torch.testing.assert_close(got[..., :1], plain[..., :1])


def test_the_flip_test_answers_each_crop_alone_at_the_nets_grid():
    torch.manual_seed(0)
    net = CameraNet(CameraNetConfig(deconv_channels=16)).eval()
    x = torch.randn(4, 3, 64, 64)
    with torch.no_grad():
        for p in net.parameters():  # an untrained head answers a constant
            p.add_(0.1 * torch.randn_like(p))
        batch, one = FlipTest(net)(x), FlipTest(net)(x[2:3])
        plain = net(x)
    assert batch.shape == plain.shape == (4, K, 16, 16)
    torch.testing.assert_close(batch[2:3], one)
    assert not torch.allclose(batch, plain)
    assert FlipTest(net).cfg is net.cfg
