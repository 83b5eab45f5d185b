#!/usr/bin/env python3
"""Train millinav's UNet localizer (segmentation + tip/centroid/tail keypoints) and export ONNX.

Follows the paper's recipe (RIG.md, Vision): loss = cross-entropy (mask) + 0.5 * L1 (keypoints),
Adam lr 1e-3, ReduceLROnPlateau, early stopping, flips and 90-degree rotations. Differences,
chosen for a 2-core CPU at inference: input is a 96x96 ROI (192 px crop downsampled 2x, see
services/roi/src/roi.rs) instead of 572x572, a 3-level UNet with 16/32/64 channels, and batch 32.

Keypoints come from 3 heatmaps through a spatial soft-argmax, so the exported graph outputs
coordinates directly:
  input  "image"     float32 [1, 3, 96, 96], RGB in [0, 1]
  output "seg"       float32 [1, 2, 96, 96], logits (class 1 = capsule)
  output "keypoints" float32 [1, 3, 2], (x, y) of tip, centroid, tail in input pixels
  output "presence"  float32 [1, 1], logit that a capsule is in the crop

Usage: python3 train.py --data DATASET_DIR --out model.onnx [--epochs 60]
"""
import argparse
import json
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

INPUT = 96


def load_split(directory):
    labels = np.genfromtxt(f"{directory}/labels.csv", delimiter=",", skip_header=1, dtype=np.float64)
    labels = labels.reshape(-1, 11)
    n = labels.shape[0]
    images = np.fromfile(f"{directory}/images.u8", dtype=np.uint8).reshape(n, INPUT, INPUT, 3)
    masks = np.fromfile(f"{directory}/masks.u8", dtype=np.uint8).reshape(n, INPUT, INPUT)
    has = labels[:, 1].astype(np.float32)
    kps = labels[:, 2:8].reshape(n, 3, 2).astype(np.float32)
    return images, masks, has, kps


def conv_block(cin, cout):
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class UNet(nn.Module):
    def __init__(self, c=(16, 32, 64)):
        super().__init__()
        self.enc1 = conv_block(3, c[0])
        self.enc2 = conv_block(c[0], c[1])
        self.bottom = conv_block(c[1], c[2])
        self.up2 = nn.ConvTranspose2d(c[2], c[1], 2, stride=2)
        self.dec2 = conv_block(2 * c[1], c[1])
        self.up1 = nn.ConvTranspose2d(c[1], c[0], 2, stride=2)
        self.dec1 = conv_block(2 * c[0], c[0])
        self.seg = nn.Conv2d(c[0], 2, 1)
        self.heat = nn.Conv2d(c[0], 3, 1)
        self.presence = nn.Linear(c[2], 1)
        ys, xs = torch.meshgrid(torch.arange(INPUT, dtype=torch.float32), torch.arange(INPUT, dtype=torch.float32), indexing="ij")
        self.register_buffer("grid_x", xs.reshape(1, 1, -1))
        self.register_buffer("grid_y", ys.reshape(1, 1, -1))

    def forward(self, x):
        e1 = self.enc1(x)
        e2 = self.enc2(F.max_pool2d(e1, 2))
        b = self.bottom(F.max_pool2d(e2, 2))
        d2 = self.dec2(torch.cat([self.up2(b), e2], 1))
        d1 = self.dec1(torch.cat([self.up1(d2), e1], 1))
        seg = self.seg(d1)
        heat = self.heat(d1).flatten(2)
        prob = torch.softmax(heat, dim=2)
        kx = (prob * self.grid_x).sum(2)
        ky = (prob * self.grid_y).sum(2)
        keypoints = torch.stack([kx, ky], dim=2)
        presence = self.presence(b.mean(dim=(2, 3)))
        return seg, keypoints, presence


def augment(img, mask, kps):
    """Random flips and 90-degree rotations of a batch (N,3,H,W), (N,H,W), (N,3,2)."""
    s = INPUT - 1
    if np.random.rand() < 0.5:
        img, mask = img.flip(3), mask.flip(2)
        kps = kps.clone()
        kps[..., 0] = s - kps[..., 0]
    if np.random.rand() < 0.5:
        img, mask = img.flip(2), mask.flip(1)
        kps = kps.clone()
        kps[..., 1] = s - kps[..., 1]
    k = np.random.randint(4)
    for _ in range(k):
        # rot90 counter-clockwise in the (H, W) plane: (x, y) -> (y, s - x)
        img, mask = torch.rot90(img, 1, (2, 3)), torch.rot90(mask, 1, (1, 2))
        kps = torch.stack([kps[..., 1], s - kps[..., 0]], dim=-1)
    return img, mask, kps


def loss_fn(seg, kp, presence, mask, kps, has):
    ce = F.cross_entropy(seg, mask.long())
    weight = has[:, None, None]
    l1 = (weight * (kp - kps).abs() / INPUT).sum() / (weight.sum() * 6 + 1e-6)
    pres = F.binary_cross_entropy_with_logits(presence[:, 0], has)
    return ce + 0.5 * l1 + 0.1 * pres


def to_tensors(images, masks, has, kps, device):
    return (
        torch.from_numpy(images).permute(0, 3, 1, 2).float().div(255.0).to(device),
        torch.from_numpy(masks).to(device),
        torch.from_numpy(has).to(device),
        torch.from_numpy(kps).to(device),
    )


def evaluate(model, data, device, batch=256):
    model.eval()
    images, masks, has, kps = data
    tp = fp = fn = 0
    errors = []
    total = 0.0
    with torch.no_grad():
        for i in range(0, images.shape[0], batch):
            x, m, h, k = images[i:i + batch], masks[i:i + batch], has[i:i + batch], kps[i:i + batch]
            seg, kp, pres = model(x)
            total += loss_fn(seg, kp, pres, m, k, h).item() * x.shape[0]
            pred = seg.argmax(1)
            tp += ((pred == 1) & (m == 1)).sum().item()
            fp += ((pred == 1) & (m == 0)).sum().item()
            fn += ((pred == 0) & (m == 1)).sum().item()
            sel = h > 0.5
            if sel.any():
                errors.append((kp[sel] - k[sel]).norm(dim=2).cpu().numpy())
    err = np.concatenate(errors) if errors else np.zeros((0, 3))
    return {
        "loss": total / images.shape[0],
        "precision": tp / max(tp + fp, 1),
        "recall": tp / max(tp + fn, 1),
        "iou": tp / max(tp + fp + fn, 1),
        "centroid_err_px_median": float(np.median(err[:, 1])) if len(err) else float("nan"),
        "tip_err_px_median": float(np.median(err[:, 0])) if len(err) else float("nan"),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="dataset dir with train/ val/ test/")
    ap.add_argument("--out", required=True, help="output .onnx path")
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--patience", type=int, default=10, help="early stopping patience (epochs)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--metrics", default=None, help="write final metrics JSON here")
    args = ap.parse_args()
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    train = to_tensors(*load_split(f"{args.data}/train"), device)
    val = to_tensors(*load_split(f"{args.data}/val"), device)
    test = to_tensors(*load_split(f"{args.data}/test"), device)
    model = UNet().to(device)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=4)
    best, best_state, stale = float("inf"), None, 0
    n = train[0].shape[0]
    start = time.time()
    for epoch in range(args.epochs):
        model.train()
        perm = torch.randperm(n, device=device)
        for i in range(0, n, args.batch):
            idx = perm[i:i + args.batch]
            x, m, k = augment(train[0][idx], train[1][idx], train[3][idx])
            seg, kp, pres = model(x)
            loss = loss_fn(seg, kp, pres, m, k, train[2][idx])
            opt.zero_grad()
            loss.backward()
            opt.step()
        metrics = evaluate(model, val, device)
        sched.step(metrics["loss"])
        print(f"epoch {epoch:3d} val {json.dumps({k: round(v, 4) for k, v in metrics.items()})} lr {opt.param_groups[0]['lr']:.1e} t {time.time() - start:.0f}s", flush=True)
        if metrics["loss"] < best - 1e-5:
            best, stale = metrics["loss"], 0
            best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}
        else:
            stale += 1
            if stale >= args.patience:
                print(f"early stop at epoch {epoch}")
                break
    model.load_state_dict(best_state)
    final = evaluate(model, test, device)
    final["epochs"] = epoch + 1
    final["train_samples"] = n
    print("test", json.dumps(final))
    if args.metrics:
        with open(args.metrics, "w") as f:
            json.dump(final, f, indent=2)
    model = model.cpu().eval()
    dummy = torch.zeros(1, 3, INPUT, INPUT)
    torch.onnx.export(
        model, dummy, args.out, input_names=["image"], output_names=["seg", "keypoints", "presence"],
        opset_version=17, dynamo=False,
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
