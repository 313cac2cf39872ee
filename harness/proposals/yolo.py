"""Proposer ``yolo``: a YOLO-family detector exported to TorchScript, loaded from a local file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from harness.boxes import nms
from harness.errors import ConfigError
from harness.methods import proposer
from harness.proposals.config import ProposalsConfig, YoloConfig


class YoloProposer:
    """A YOLO-family detector exported to TorchScript or ONNX (``yolo export format=onnx``).

    A ``.onnx`` file runs through OpenCV's ``cv2.dnn`` (no new runtime), any other file through
    ``torch.jit.load``. The model maps a float ``(B, 3, S, S)`` RGB batch in [0, 1] to either
    ``(B, 4 + nc, N)`` (YOLOv8/11 layout: cx, cy, w, h, class scores) or ``(B, N, 5 + nc)``
    (YOLOv5 layout: cx, cy, w, h, objectness, class scores), in input pixels.
    Images are letterboxed to S.
    """

    def __init__(self, cfg: YoloConfig) -> None:
        import torch

        if not cfg.weights:
            raise ConfigError(
                "[proposals.yolo] weights is not set: export a model to TorchScript on a "
                "machine with "
                "ultralytics (yolo export model=yolov8n.pt format=torchscript) and give its "
                "local path"
            )
        path = Path(cfg.weights).expanduser()
        if not path.exists():
            raise ConfigError(
                f"YOLO weights file {path} does not exist; nothing is downloaded at run "
                "time. Export one with "
                "'yolo export model=yolov8n.pt format=torchscript' where ultralytics is "
                "installed and copy the "
                ".torchscript file here"
            )
        self.cfg = cfg
        self.onnx: Any = None
        if path.suffix.lower() == ".onnx":
            try:
                self.onnx = cv2.dnn.readNetFromONNX(str(path))
            except cv2.error as err:
                raise ConfigError(
                    f"{path}: not an ONNX model OpenCV can read: {str(err).strip()[-200:]}"
                ) from None
            return
        dev = cfg.device
        self.device = torch.device(
            "cuda"
            if dev == "auto" and torch.cuda.is_available()
            else ("cpu" if dev == "auto" else dev)
        )
        try:
            self.model = torch.jit.load(str(path), map_location=self.device).eval()
        except (RuntimeError, ValueError) as err:
            raise ConfigError(f"{path}: not a TorchScript model: {err}") from None

    def _letterbox(self, rgb: np.ndarray) -> tuple[np.ndarray, float, tuple[float, float]]:
        s = self.cfg.imgsz
        h, w = rgb.shape[:2]
        r = min(s / h, s / w)
        nw, nh = round(w * r), round(h * r)
        out = np.full((s, s, 3), 114, np.uint8)
        px, py = (s - nw) // 2, (s - nh) // 2
        out[py : py + nh, px : px + nw] = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_LINEAR)
        return out, r, (px, py)

    def __call__(self, images: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Boxes, scores and class ids for each image (boxes in the image's pixels)."""
        import torch

        results = []
        if self.onnx is not None:  # cv2.dnn: one image at a time (exports often fix the batch)
            for im in images:
                box, r, (px, py) = self._letterbox(im)
                blob = np.ascontiguousarray(box.transpose(2, 0, 1)[None], np.float32) / 255.0
                self.onnx.setInput(blob)
                y = np.asarray(self.onnx.forward(), np.float32)
                results.append(self._decode(y[0], r, px, py, im.shape[1], im.shape[0]))
            return results
        for i in range(0, len(images), self.cfg.batch):
            chunk = images[i : i + self.cfg.batch]
            lb = [self._letterbox(im) for im in chunk]
            x = (
                torch.from_numpy(np.stack([b[0] for b in lb]))
                .to(self.device)
                .permute(0, 3, 1, 2)
                .float()
                / 255.0
            )
            with torch.inference_mode():
                y = self.model(x)
            if isinstance(y, (list, tuple)):
                y = y[0]
            y = y.float().cpu().numpy()
            for pred, (_, r, (px, py)), im in zip(y, lb, chunk, strict=True):
                results.append(self._decode(pred, r, px, py, im.shape[1], im.shape[0]))
        return results

    def _decode(
        self, pred: np.ndarray, r: float, px: float, py: float, w: int, h: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if pred.shape[0] < pred.shape[1]:  # (4 + nc, N): v8 layout
            pred = pred.T
            xywh, cls_scores = pred[:, :4], pred[:, 4:]
        else:  # (N, 5 + nc): v5 layout
            xywh, cls_scores = pred[:, :4], pred[:, 5:] * pred[:, 4:5]
        if cls_scores.shape[1] == 0:
            return np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64)
        cls = cls_scores.argmax(1)
        score = cls_scores[np.arange(len(cls)), cls]
        ok = score >= self.cfg.conf
        xywh, score, cls = xywh[ok], score[ok], cls[ok]
        boxes = np.column_stack(
            [
                xywh[:, 0] - xywh[:, 2] / 2,
                xywh[:, 1] - xywh[:, 3] / 2,
                xywh[:, 0] + xywh[:, 2] / 2,
                xywh[:, 1] + xywh[:, 3] / 2,
            ]
        )
        boxes = (boxes - [px, py, px, py]) / r
        boxes = np.clip(boxes, 0, [w, h, w, h]).astype(np.float64)
        area_ok = (boxes[:, 2] - boxes[:, 0] >= 1) & (boxes[:, 3] - boxes[:, 1] >= 1)
        boxes, score, cls = boxes[area_ok], score[area_ok], cls[area_ok]
        keep = nms(boxes, score, self.cfg.iou, cls)[: self.cfg.max_det]
        return boxes[keep], score[keep].astype(np.float64), cls[keep].astype(np.int64)


@proposer("yolo")
def yolo_proposer(cfg: ProposalsConfig) -> YoloProposer:
    """``yolo`` with ``[proposals.yolo]``: the network, called on a batch of images."""
    return YoloProposer(cfg.yolo)
