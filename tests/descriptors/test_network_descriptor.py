"""``harness.descriptors.network``: a user's own network (TorchScript, ONNX) as the descriptor.

The tests build and save the small networks themselves (nothing is downloaded); the ONNX file
runs through OpenCV's ``cv2.dnn``, the TorchScript file through torch, and both must give what the
network gives in torch on the same normalised input.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from harness.cli import main
from harness.descriptors import make_descriptor
from harness.descriptors.config import DescriptorConfig
from harness.descriptors.network import pool
from harness.errors import ConfigError
from harness.proposals.config import YoloConfig
from harness.proposals.yolo import YoloProposer

from ..conftest import ROOT
from ..proposals.test_proposals import TinyYolo

FIXTURE_TOML = ROOT / "datasets" / "fixture.toml"


class Tiny(torch.nn.Module):
    """A small convolutional feature extractor: (N, 3, 32, 32) -> (N, 8, 8, 8)."""

    def __init__(self) -> None:
        super().__init__()
        self.body = torch.nn.Sequential(
            torch.nn.Conv2d(3, 8, 3, padding=1),
            torch.nn.ReLU(),
            torch.nn.MaxPool2d(2),
            torch.nn.Conv2d(8, 8, 3, padding=1),
            torch.nn.ReLU(),
            torch.nn.MaxPool2d(2),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x)


def descriptor_config(lines: str) -> str:
    """The fixture config with its ``[descriptor]`` table replaced by ``lines``."""
    text = FIXTURE_TOML.read_text().replace('"annotations/', f'"{ROOT}/annotations/')
    text = text.replace('"datasets/models"', f'"{ROOT}/datasets/models"')
    head, rest = text.split("[descriptor]\n", 1)
    return head + "[descriptor]\n" + lines + "\n\n[" + rest.split("\n[", 1)[1]


def save_networks(tmp: Path) -> tuple[torch.nn.Module, Path, Path]:
    torch.manual_seed(0)
    net = Tiny().eval()
    x = torch.rand(2, 3, 32, 32)
    ts = tmp / "tiny.pt"
    torch.jit.trace(net, x).save(str(ts))  # deprecated in torch, still what most users have
    onnx = tmp / "tiny.onnx"
    torch.onnx.export(
        net,
        (x,),
        str(onnx),
        dynamo=False,
        input_names=["x"],
        output_names=["y"],
        dynamic_axes={"x": {0: "n"}, "y": {0: "n"}},
    )
    return net, ts, onnx


def test_both_formats_give_the_networks_pooled_output(tmp_path: Path) -> None:
    net, ts, onnx = save_networks(tmp_path)
    crops = np.random.default_rng(1).integers(0, 256, (5, 32, 32, 3), dtype=np.uint8)
    mean, std = (0.5, 0.4, 0.3), (0.2, 0.25, 0.3)
    x = (crops / 255.0 - np.array(mean)) / np.array(std)
    with torch.no_grad():
        fmap = net(torch.from_numpy(x.transpose(0, 3, 1, 2)).float()).numpy()
    for how, want in (
        ("avg", fmap.mean((2, 3))),
        ("max", fmap.max((2, 3))),
        ("gem", (np.clip(fmap, 1e-6, None) ** 3).mean((2, 3)) ** (1 / 3)),
    ):
        for name, path in (("torchscript", ts), ("onnx", onnx)):
            cfg = DescriptorConfig(
                name=name, path=str(path), input_size=32, mean=mean, std=std, pooling=how
            )
            got = make_descriptor(cfg).encode(crops)
            assert got.shape == (5, 8)
            np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5, err_msg=f"{name} {how}")
    assert pool(np.ones((2, 7)), "gem").shape == (2, 7)  # vectors pass as they are


def test_a_missing_or_foreign_network_file_is_one_error(tmp_path: Path) -> None:
    (tmp_path / "not.onnx").write_text("hello")
    with pytest.raises(ConfigError, match="not an ONNX model OpenCV can read"):
        make_descriptor(DescriptorConfig(name="onnx", path=str(tmp_path / "not.onnx"))).encode(
            np.zeros((1, 32, 32, 3), np.uint8)
        )
    (tmp_path / "c.toml").write_text(descriptor_config('name = "onnx"\npath = "missing.onnx"'))
    from harness.config.assemble import load_config

    with pytest.raises(ConfigError, match=r"\[descriptor\] path = .*missing.onnx.*existing file"):
        load_config(tmp_path / "c.toml")


def test_a_run_with_an_onnx_descriptor_as_a_user_types_it(
    local_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    p, _, run = local_run
    _, _, onnx = save_networks(tmp_path)
    cfg = tmp_path / "net.toml"
    cfg.write_text(
        descriptor_config(f'name = "onnx"\npath = "{onnx}"\ninput_size = 32\npooling = "gem"')
    )
    out = tmp_path / "o"
    shutil.copytree(run / "cache", out / "cache")  # ingest, pairs, proposals: not recomputed
    shutil.copy(run / ".dbl-harness.json", out / ".dbl-harness.json")
    argv = ["reproduce", "--config", str(cfg), "--data-root", str(p.cfg.data_root)]
    assert main([*argv, "--out", str(out)]) == 0
    assert "localizer onnx" in capsys.readouterr().out
    loc = pd.read_csv(out / "localization.csv")
    row = loc[(loc["proposal_method"] == "all") & (loc["season_pair"] == "all")].iloc[0]
    ranks = pd.read_parquet(out / "ranks.parquet")
    assert row["subimages"] == len(ranks)  # every ranked subimage counted
    assert row["recall_at_1"] == pytest.approx((ranks["rank"] == 1).mean(), abs=5e-5)
    assert row["recall_at_1"] > 2 * row["chance_recall_at_1"]  # the network localizes
    assert (out / "report.html").exists()


def test_yolo_weights_as_onnx_give_the_torchscript_boxes(tmp_path: Path) -> None:
    torch.manual_seed(0)
    model = TinyYolo().eval()
    torch.jit.script(model).save(str(tmp_path / "y.torchscript"))
    torch.onnx.export(model, (torch.rand(1, 3, 64, 64),), str(tmp_path / "y.onnx"), dynamo=False)
    imgs = [
        np.random.default_rng(i).integers(0, 256, (60, 40, 3), dtype=np.uint8) for i in range(3)
    ]
    ts = YoloProposer(YoloConfig(weights=str(tmp_path / "y.torchscript"), imgsz=64, batch=1))
    ox = YoloProposer(YoloConfig(weights=str(tmp_path / "y.onnx"), imgsz=64, batch=1))
    for (b1, s1, c1), (b2, s2, c2) in zip(ts(imgs), ox(imgs), strict=True):
        assert len(b1) > 0 and b1.shape == b2.shape
        np.testing.assert_allclose(b1, b2, atol=1e-3)
        np.testing.assert_allclose(s1, s2, atol=1e-5)
        np.testing.assert_array_equal(c1, c2)
