#!/usr/bin/env python3
"""Checks that the JAX trainer computes the committed model: on the committed test crops
(testset/), the graph export.py writes from the committed weights (model/unet_roi96.npz) and
train.py's own forward pass (inference mode) must both give what the committed
model/unet_roi96.onnx gives in onnxruntime, within TOLERANCE of each output.

Usage: python3 tools/unet/check_export.py [--weights W.npz] [--reference R.onnx] [--crops SPLIT_DIR]
Prints the largest absolute difference per output and exits 1 if one is over the tolerance.
"""
import argparse
import os
import sys
import tempfile

import numpy as np
import onnxruntime as ort

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import export  # noqa: E402
import train  # noqa: E402
import weights  # noqa: E402

OUTPUTS = ("seg", "keypoints", "presence")
# Largest absolute difference allowed per output. Logits: 1e-3. Keypoints are in input pixels
# (0 to 95), each the expectation of a softmax over the 9216 pixel coordinates, summed in float32
# in another order by each implementation: 1e-2 px (a thousandth of a millimetre on the floor).
TOLERANCE = {"seg": 1e-3, "keypoints": 1e-2, "presence": 1e-3}


def run_onnx(path, images):
    session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    runs = [session.run(list(OUTPUTS), {"image": image[None]}) for image in images]
    return [np.concatenate([run[k] for run in runs]) for k in range(len(OUTPUTS))]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--weights", default=f"{HERE}/model/unet_roi96.npz")
    ap.add_argument("--reference", default=f"{HERE}/model/unet_roi96.onnx")
    ap.add_argument("--crops", default=f"{HERE}/testset")
    args = ap.parse_args()
    arrays = weights.load(args.weights)
    params, state = train.from_arrays(arrays, args.weights)
    images = np.asarray(train.to_input(train.load_split(args.crops)[0]))
    reference = run_onnx(args.reference, images)
    with tempfile.TemporaryDirectory() as tmp:
        exported = os.path.join(tmp, "exported.onnx")
        export.export(train.to_arrays(params, state), exported)
        candidates = {"export.py's graph": run_onnx(exported, images)}
    outputs, _ = train.forward(params, state, images, train=False)
    candidates["train.py's forward"] = [np.asarray(o) for o in outputs]
    over = []
    print(f"{images.shape[0]} crops of {args.crops}, against {args.reference}")
    for name, got in candidates.items():
        diffs = [float(np.abs(g - r).max()) for g, r in zip(got, reference)]
        print(f"  {name}: max |diff| " + ", ".join(f"{o} {d:.2e}" for o, d in zip(OUTPUTS, diffs)))
        over += [f"{name}: {o} {d:.2e} > {TOLERANCE[o]:.0e}" for o, d in zip(OUTPUTS, diffs) if d > TOLERANCE[o]]
    if over:
        sys.exit("check_export: over the tolerance: " + "; ".join(over))
    print("ok: every difference within " + ", ".join(f"{o} {t:.0e}" for o, t in TOLERANCE.items()))


if __name__ == "__main__":
    main()
