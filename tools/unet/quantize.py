#!/usr/bin/env python3
"""Post-training static int8 quantization of millinav's UNet localizer for the CPU.

QDQ format, int8 per-channel weights in 7 bits (reduce_range: exact on CPUs with and without
VNNI) and uint8 activations,
calibrated on twin renders exported by `unet-dataset` with seeds that the committed test set does
not use. Inputs and outputs keep their names, shapes and float32 types, so the vision service
loads either model. Evaluate the result with
`vision-eval --model tools/unet/model/unet_roi96_int8.onnx` before switching to it.

Needs the `onnx` package next to onnxruntime (`pip install onnx`).
Usage: python3 quantize.py --calib SPLIT_DIR [--calib SPLIT_DIR ...] --model IN.onnx --out OUT.onnx
       [--samples 300]
"""
import argparse
import os
import tempfile

import numpy as np
import onnx
from onnxruntime.quantization import (
    CalibrationDataReader,
    CalibrationMethod,
    QuantFormat,
    QuantType,
    quantize_static,
)
from onnxruntime.quantization.shape_inference import quant_pre_process

INPUT = 96
def keypoint_head(path):
    """The nodes from the heatmap convolution to the "keypoints" output, which stay float: the
    soft-argmax over 96x96 heatmaps needs more than 8 bits of logit resolution (quantized, the
    tip error grew from 0.009 to 0.2 mm on the test set). Found in the graph, so any depth or
    width of train.py's UNet quantizes the same way."""
    graph = onnx.load(path).graph
    producer = {output: node for node in graph.node for output in node.output}
    head, pending = [], ["keypoints"]
    while pending:
        node = producer.get(pending.pop())
        if node is None or node.name in head:
            continue
        head.append(node.name)
        if node.op_type != "Conv":  # the heatmap convolution is the head's first node
            pending.extend(node.input)
    if not any(name.startswith("/heat/") for name in head):
        raise SystemExit(f"{path}: no heatmap convolution (/heat/Conv) before the keypoints output")
    return head


class RoiReader(CalibrationDataReader):
    """Feeds ROI crops exactly as the service does: RGB in [0, 1], NCHW float32."""

    def __init__(self, directories, limit):
        crops = []
        for directory in directories:
            n = sum(1 for _ in open(os.path.join(directory, "labels.csv"))) - 1
            images = np.fromfile(os.path.join(directory, "images.u8"), dtype=np.uint8)
            crops.extend(images.reshape(n, INPUT, INPUT, 3)[:limit])
        self.batches = iter(
            [img.transpose(2, 0, 1)[None].astype(np.float32) / 255.0 for img in crops]
        )

    def get_next(self):
        image = next(self.batches, None)
        return None if image is None else {"image": image}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--calib", required=True, action="append",
        help="unet-dataset split directory; repeat to mix (e.g. clean and shifted crops)",
    )
    parser.add_argument("--model", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--samples", type=int, default=300, help="crops per --calib directory")
    parser.add_argument(
        "--exclude", nargs="*", default=[], help="more node names to keep in float"
    )
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        prepared = os.path.join(tmp, "prepared.onnx")
        # Static shapes: the symbolic pass (and its sympy dependency) is not needed.
        quant_pre_process(args.model, prepared, skip_symbolic_shape=True)
        quantize_static(
            prepared,
            args.out,
            RoiReader(args.calib, args.samples),
            quant_format=QuantFormat.QDQ,
            per_channel=True,
            weight_type=QuantType.QInt8,
            activation_type=QuantType.QUInt8,
            calibrate_method=CalibrationMethod.MinMax,
            nodes_to_exclude=keypoint_head(prepared) + args.exclude,
            # 7-bit weights: on x86 CPUs without VNNI (AVX2-only, AVX-512 without VNNI) ONNX
            # Runtime multiplies u8 x s8 with VPMADDUBSW, whose 16-bit pair sums saturate with
            # full-range weights. Quantized without this, the model lost the capsule there
            # (precision 21 %, centroid p95 4.3 mm on an AVX2-only AMD EPYC) while it was exact
            # on VNNI machines.
            reduce_range=True,
        )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
