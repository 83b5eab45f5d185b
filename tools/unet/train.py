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

Training applies the camera's shifts to every batch (augment.py: scale, occlusion, colour cast,
lighting, shadow, glare, bubbles, texture, blur, noise, JPEG) on top of flips and rotations;
early stopping watches the validation loss on clean crops and on a fixed shifted copy of them.
Beside the ONNX file it writes the PyTorch weights (.pt), from which --init fine-tunes.
Two departures from the paper's recipe, off by default: --iou-weight adds a soft-IoU term to
the loss, --ema keeps a moving average of the weights (README, Vision: tried on a GPU, no gain).

Usage: python3 train.py --data DATASET_DIR [--data MORE_TRAIN_DIR ...] --out model.onnx
       [--epochs 60] [--init model.pt --lr 3e-4] [--augment flips] [--iou-weight 0.5] [--ema 0.999]
"""
import argparse
import json
import os
import sys
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import augment as camera  # noqa: E402  (beside this script)

INPUT = 96
HEADER = "index,has_robot,tip_x,tip_y,centroid_x,centroid_y,tail_x,tail_y,crop_col0,crop_row0,mm_per_px"


def load_labels(directory):
    path = f"{directory}/labels.csv"
    with open(path) as f:
        header = f.readline().strip()
    if header != HEADER:
        sys.exit(f"{path}: unexpected header (want {HEADER})")
    return np.genfromtxt(path, delimiter=",", skip_header=1, dtype=np.float64).reshape(-1, 11)


def load_split(directory):
    labels = load_labels(directory)
    n = labels.shape[0]
    if n == 0:
        sys.exit(f"{directory}: empty split")
    images = np.fromfile(f"{directory}/images.u8", dtype=np.uint8)
    masks = np.fromfile(f"{directory}/masks.u8", dtype=np.uint8)
    if images.size != n * INPUT * INPUT * 3 or masks.size != n * INPUT * INPUT:
        sys.exit(f"{directory}: images.u8/masks.u8 do not hold {n} crops of {INPUT}x{INPUT}")
    images = images.reshape(n, INPUT, INPUT, 3)
    masks = masks.reshape(n, INPUT, INPUT)
    has = labels[:, 1].astype(np.float32)
    kps = labels[:, 2:8].reshape(n, 3, 2).astype(np.float32)
    return images, masks, has, kps


def save_split(directory, images, masks, has, kps, mm_per_px):
    """Writes crops (tensors as training holds them) in unet-dataset's split format."""
    os.makedirs(directory, exist_ok=True)
    img = (images.permute(0, 2, 3, 1).clamp(0, 1) * 255).round().byte().cpu().numpy()
    img.tofile(f"{directory}/images.u8")
    masks.byte().cpu().numpy().tofile(f"{directory}/masks.u8")
    k = kps.cpu().numpy().reshape(-1, 6)
    with open(f"{directory}/labels.csv", "w") as f:
        f.write(HEADER + "\n")
        for i in range(img.shape[0]):
            coords = ",".join(f"{v:.4f}" for v in k[i])
            f.write(f"{i},{int(has[i].item() > 0.5)},{coords},0,0,{mm_per_px}\n")


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
    """`levels` resolutions (the input's and levels - 1 halvings), `width` channels at the first,
    doubling at each. The default, 3 levels of 16/32/64, is the committed model; the module names
    (enc1.., bottom, upK, decK) are the same at every depth, so .pt files stay loadable."""

    def __init__(self, levels=3, width=16):
        super().__init__()
        if levels < 2 or width < 1 or INPUT % 2 ** (levels - 1):
            raise ValueError(f"a UNet of {levels} levels and width {width} does not fit a {INPUT} px input")
        c = [width * 2 ** i for i in range(levels)]
        self.levels = levels
        for k in range(1, levels):
            self.add_module(f"enc{k}", conv_block(3 if k == 1 else c[k - 2], c[k - 1]))
        self.bottom = conv_block(c[-2], c[-1])
        for k in range(levels - 1, 0, -1):
            self.add_module(f"up{k}", nn.ConvTranspose2d(c[k], c[k - 1], 2, stride=2))
            self.add_module(f"dec{k}", conv_block(2 * c[k - 1], c[k - 1]))
        self.seg = nn.Conv2d(c[0], 2, 1)
        self.heat = nn.Conv2d(c[0], 3, 1)
        self.presence = nn.Linear(c[-1], 1)
        ys, xs = torch.meshgrid(torch.arange(INPUT, dtype=torch.float32), torch.arange(INPUT, dtype=torch.float32), indexing="ij")
        self.register_buffer("grid_x", xs.reshape(1, 1, -1))
        self.register_buffer("grid_y", ys.reshape(1, 1, -1))

    @staticmethod
    def shape_of(state):
        """(levels, width) of the UNet whose state dict this is."""
        levels = 1 + sum(1 for key in state if key.startswith("enc") and key.endswith(".0.weight"))
        return levels, state["enc1.0.weight"].shape[0]

    def forward(self, x):
        skips = []
        for k in range(1, self.levels):
            x = getattr(self, f"enc{k}")(x if k == 1 else F.max_pool2d(x, 2))
            skips.append(x)
        b = self.bottom(F.max_pool2d(x, 2))
        d = b
        for k in range(self.levels - 1, 0, -1):
            d = getattr(self, f"dec{k}")(torch.cat([getattr(self, f"up{k}")(d), skips[k - 1]], 1))
        seg = self.seg(d)
        heat = self.heat(d).flatten(2)
        prob = torch.softmax(heat, dim=2)
        kx = (prob * self.grid_x).sum(2)
        ky = (prob * self.grid_y).sum(2)
        keypoints = torch.stack([kx, ky], dim=2)
        presence = self.presence(b.mean(dim=(2, 3)))
        return seg, keypoints, presence


def flips(img, mask, kps):
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


def soft_jaccard(seg, mask):
    """1 - soft IoU of the capsule class over the whole batch: the same pixel-pooled overlap that
    evaluate() and vision-eval report, made differentiable with the softmax probability."""
    p = torch.softmax(seg, dim=1)[:, 1]
    t = mask.float()
    inter = (p * t).sum()
    return 1.0 - inter / ((p + t).sum() - inter + 1.0)


def loss_fn(seg, kp, presence, mask, kps, has, iou_weight=0.0):
    ce = F.cross_entropy(seg, mask.long())
    weight = has[:, None, None]
    l1 = (weight * (kp - kps).abs() / INPUT).sum() / (weight.sum() * 6 + 1e-6)
    pres = F.binary_cross_entropy_with_logits(presence[:, 0], has)
    loss = ce + 0.5 * l1 + 0.1 * pres
    if iou_weight > 0.0:
        loss = loss + iou_weight * soft_jaccard(seg, mask)
    return loss


def to_tensors(images, masks, has, kps, device):
    return (
        torch.from_numpy(images).permute(0, 3, 1, 2).float().div(255.0).to(device),
        torch.from_numpy(masks).to(device),
        torch.from_numpy(has).to(device),
        torch.from_numpy(kps).to(device),
    )


def evaluate(model, data, device, batch=256, iou_weight=0.0):
    model.eval()
    images, masks, has, kps = data
    tp = fp = fn = 0
    errors = []
    total = 0.0
    with torch.no_grad():
        for i in range(0, images.shape[0], batch):
            x, m, h, k = images[i:i + batch], masks[i:i + batch], has[i:i + batch], kps[i:i + batch]
            seg, kp, pres = model(x)
            total += loss_fn(seg, kp, pres, m, k, h, iou_weight).item() * x.shape[0]
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


def concat(parts):
    return tuple(torch.cat(xs) for xs in zip(*parts))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, action="append",
                    help="dataset dir with train/ (val/ test/ from the first); repeat to add training crops")
    ap.add_argument("--out", required=True, help="output .onnx path (the .pt weights go beside it)")
    ap.add_argument("--epochs", type=int, default=60)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--patience", type=int, default=10, help="early stopping patience (epochs)")
    ap.add_argument("--max-minutes", type=float, default=None, help="stop after this long (best weights kept)")
    ap.add_argument("--augment", choices=["camera", "flips"], default="camera",
                    help="camera: flips + camera shifts (augment.py); flips: flips and rotations only")
    ap.add_argument("--init", default=None, help="start from these weights (.pt written by this script)")
    ap.add_argument("--dump-augmented", default=None,
                    help="also write this many shifted training crops as a split to DIR (e.g. quantization calibration)",
                    nargs=2, metavar=("DIR", "COUNT"))
    ap.add_argument("--shift-chance", action="append", default=[], metavar="FAMILY=P",
                    help="train with this chance per crop for one camera-shift family (augment.FAMILIES: "
                         + ", ".join(camera.FAMILIES) + "); repeat for more. Validation keeps the defaults")
    ap.add_argument("--iou-weight", type=float, default=0.0,
                    help="add this weight x (1 - soft IoU of the mask) to the paper's loss (CE + 0.5 L1); 0: the paper's")
    ap.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                    help="evaluate, early-stop and export an exponential moving average of the weights "
                         "(e.g. 0.999 per step); 0: the weights as trained")
    ap.add_argument("--levels", type=int, default=None,
                    help="resolutions of the UNet (default 3, or --init's); each more sees twice as far and costs more per crop")
    ap.add_argument("--width", type=int, default=None,
                    help="channels at full resolution, doubling per level (default 16, or --init's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--metrics", default=None, help="write final metrics JSON here")
    args = ap.parse_args()
    chance = {}
    for item in args.shift_chance:
        family, _, value = item.partition("=")
        try:
            p = float(value)
        except ValueError:
            p = float("nan")
        if family not in camera.FAMILIES or not 0.0 <= p <= 1.0:
            ap.error(f"--shift-chance {item!r}: expected FAMILY=P with FAMILY one of "
                     f"{', '.join(camera.FAMILIES)} and P a number in [0, 1]")
        chance[family] = p
    if not 0.0 <= args.iou_weight <= 10.0:
        ap.error(f"--iou-weight {args.iou_weight}: expected a number in [0, 10]")
    if args.levels is not None and not 2 <= args.levels <= 5:
        ap.error(f"--levels {args.levels}: expected 2 to 5 (the 96 px input halves at each)")
    if args.width is not None and not 4 <= args.width <= 64:
        ap.error(f"--width {args.width}: expected 4 to 64 channels")
    if not (args.ema == 0.0 or 0.9 <= args.ema < 1.0):
        ap.error(f"--ema {args.ema}: expected 0 (off) or a decay in [0.9, 1)")
    # The starting weights' shape before any data is read, so a wrong --init fails at once.
    init_state, shape = None, (args.levels or 3, args.width or 16)
    if args.init:
        if not os.path.isfile(args.init):
            ap.error(f"--init {args.init}: no such file")
        init_state = torch.load(args.init, map_location="cpu")
        shape = UNet.shape_of(init_state)
        if (args.levels or shape[0], args.width or shape[1]) != shape:
            sys.exit(f"--init {args.init}: a UNet of {shape[0]} levels and width {shape[1]}, "
                     f"not the --levels {args.levels or shape[0]} --width {args.width or shape[1]} asked for")
    # The output folders now, not after the training: a run is never lost to a missing folder.
    for path in (args.out, args.metrics):
        if path and os.path.dirname(path):
            os.makedirs(os.path.dirname(path), exist_ok=True)
    torch.manual_seed(args.seed)
    np.random.seed(args.seed)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    train = concat([to_tensors(*load_split(f"{d}/train"), device) for d in args.data])
    val = to_tensors(*load_split(f"{args.data[0]}/val"), device)
    test_dir = f"{args.data[0]}/test"
    test = to_tensors(*load_split(test_dir), device) if os.path.isdir(test_dir) else val
    # A fixed shifted copy of val (and test), so early stopping sees robustness too.
    generator_state = torch.get_rng_state(), torch.cuda.get_rng_state_all() if device == "cuda" else None
    torch.manual_seed(args.seed + 1)
    v_img, v_mask, v_kps = camera.camera_shifts(val[0], val[1], val[3])
    val_shifted = (v_img, v_mask, val[2], v_kps)
    t_img, t_mask, t_kps = camera.camera_shifts(test[0], test[1], test[3])
    test_shifted = (t_img, t_mask, test[2], t_kps)
    torch.set_rng_state(generator_state[0])
    if generator_state[1] is not None:
        torch.cuda.set_rng_state_all(generator_state[1])
    if args.dump_augmented:
        directory, count = args.dump_augmented[0], int(args.dump_augmented[1])
        idx = torch.randperm(train[0].shape[0], device=device)[:count]
        img, mask, kps = camera.camera_shifts(train[0][idx], train[1][idx], train[3][idx])
        mm_per_px = load_labels(f"{args.data[0]}/train")[0, 10]
        save_split(directory, img, mask, train[2][idx], kps, mm_per_px)
        print(f"wrote {idx.shape[0]} shifted training crops to {directory}")
    model = UNet(*shape)
    if init_state is not None:
        model.load_state_dict(init_state)
        print(f"fine-tuning from {args.init} ({shape[0]} levels, width {shape[1]})")
    model = model.to(device)
    # The weights that are evaluated and exported: the trained ones, or their moving average
    # (batch-norm statistics averaged too).
    averaged = None
    if args.ema > 0.0:
        averaged = torch.optim.swa_utils.AveragedModel(
            model, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(args.ema), use_buffers=True)
    scored = averaged.module if averaged is not None else model
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=4)
    best, best_state, stale = float("inf"), None, 0
    n = train[0].shape[0]
    start = time.time()
    epoch = -1
    for epoch in range(args.epochs):
        model.train()
        perm = torch.randperm(n, device=device)
        for i in range(0, n, args.batch):
            idx = perm[i:i + args.batch]
            x, m, k = flips(train[0][idx], train[1][idx], train[3][idx])
            if args.augment == "camera":
                x, m, k = camera.camera_shifts(x, m, k, chance)
            seg, kp, pres = model(x)
            loss = loss_fn(seg, kp, pres, m, k, train[2][idx], args.iou_weight)
            opt.zero_grad()
            loss.backward()
            opt.step()
            if averaged is not None:
                averaged.update_parameters(model)
        clean = evaluate(scored, val, device, iou_weight=args.iou_weight)
        shifted = evaluate(scored, val_shifted, device, iou_weight=args.iou_weight)
        score = clean["loss"] + shifted["loss"]
        sched.step(score)
        summary = {k: round(v, 4) for k, v in clean.items()}
        summary.update({f"shifted_{k}": round(v, 4) for k, v in shifted.items() if k in ("loss", "precision", "recall", "iou")})
        print(f"epoch {epoch:3d} val {json.dumps(summary)} lr {opt.param_groups[0]['lr']:.1e} t {time.time() - start:.0f}s", flush=True)
        if score < best - 1e-5:
            best, stale = score, 0
            best_state = {k: v.detach().clone() for k, v in scored.state_dict().items()}
        else:
            stale += 1
            if stale >= args.patience:
                print(f"early stop at epoch {epoch}")
                break
        if args.max_minutes is not None and time.time() - start > 60 * args.max_minutes:
            print(f"time limit at epoch {epoch}")
            break
    if best_state is not None:
        model.load_state_dict(best_state)
    final = evaluate(model, test, device, iou_weight=args.iou_weight)
    final["shifted"] = evaluate(model, test_shifted, device, iou_weight=args.iou_weight)
    final["epochs"] = epoch + 1
    final["train_samples"] = n
    final["augment"] = args.augment
    final["init"] = args.init
    final["shift_chance"] = chance
    final["levels"], final["width"] = model.levels, model.enc1[0].out_channels
    final["iou_weight"] = args.iou_weight
    final["ema"] = args.ema
    print("test", json.dumps(final))
    if args.metrics:
        with open(args.metrics, "w") as f:
            json.dump(final, f, indent=2)
    model = model.cpu().eval()
    torch.save(model.state_dict(), os.path.splitext(args.out)[0] + ".pt")
    dummy = torch.zeros(1, 3, INPUT, INPUT)
    torch.onnx.export(
        model, dummy, args.out, input_names=["image"], output_names=["seg", "keypoints", "presence"],
        opset_version=17, dynamo=False,
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
