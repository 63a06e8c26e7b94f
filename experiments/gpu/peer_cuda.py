"""Upstream BridgeDepthFlow (PyTorch) on a GPU, through the peer harness with its CPU shims undone.

    python experiments/gpu/peer_cuda.py train --harness-dir .peer/harness [--amp] --height 256 --width 512
    python experiments/gpu/peer_cuda.py infer --harness-dir .peer/harness --batch 1

The harness (kept outside this repository, with the upstream source it runs; BDF_SRC names the source folder)
replaces `.cuda()` with a no-op so that upstream runs on CPU. Here those three shims are put back to PyTorch's
own after the harness installs the others (Resample2d as grid_sample, np.int, the torchvision stand-in), so the
unmodified upstream train-loop body moves its tensors to the GPU itself. `--amp` runs the forward and the loss
under `torch.autocast("cuda", dtype=torch.bfloat16)` (backward and Adam in float32 as AMP does; bf16 needs no
loss scaling). Times are wall clock around `torch.cuda.synchronize()`. Prints one JSON line. Without CUDA it
runs on CPU (the dry run), and says so in "device".
"""
from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import statistics
import sys
import time


def load_harness(folder: str):
    spec = importlib.util.spec_from_file_location("peer_harness", os.path.join(folder, "harness.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=("train", "infer"))
    ap.add_argument("--harness-dir", required=True, help="folder holding the peer harness.py")
    ap.add_argument("--height", type=int, default=256, help="image height")
    ap.add_argument("--width", type=int, default=512, help="image width")
    ap.add_argument("--warp-type", type=int, default=2, help="upstream --type_of_2warp (2 = full-2)")
    ap.add_argument("--batch", type=int, default=2, help="infer: pairs per forward (train: upstream's 2 cycles)")
    ap.add_argument("--runs", type=int, default=5, help="timed runs")
    ap.add_argument("--warmup", type=int, default=2, help="untimed runs first")
    ap.add_argument("--amp", action="store_true", help="bfloat16 autocast for forward + loss")
    a = ap.parse_args(argv)

    import torch
    import torch.nn as nn
    cuda_ok = torch.cuda.is_available()
    originals = (torch.Tensor.cuda, nn.Module.cuda, torch.cuda.FloatTensor)
    h = load_harness(a.harness_dir)
    up = h.install_shims()
    if cuda_ok:  # undo the three CPU shims: upstream's own .cuda() calls now move to the GPU
        torch.Tensor.cuda, nn.Module.cuda, torch.cuda.FloatTensor = originals
    dev = torch.device("cuda" if cuda_ok else "cpu")
    sync = torch.cuda.synchronize if cuda_ok else (lambda: None)
    autocast = (lambda: torch.autocast(dev.type, dtype=torch.bfloat16)) if a.amp else contextlib.nullcontext
    torch.manual_seed(0)
    net = up["mm"].MonodepthNet().to(dev)
    g = torch.Generator(device=dev).manual_seed(1)
    times, phases = [], []
    if cuda_ok:
        torch.cuda.reset_peak_memory_stats()
    if a.mode == "infer":
        net.eval()
        with torch.no_grad():
            for i in range(a.warmup + a.runs):
                x = torch.rand(a.batch, 6, a.height, a.width, generator=g, device=dev)
                sync()
                t0 = time.perf_counter()
                with autocast():
                    net(x)
                sync()
                if i >= a.warmup:
                    times.append(time.perf_counter() - t0)
        extra = {"batch": a.batch}
    else:
        tp = h.load_train_py()
        args = h.upstream_args(a.warp_type, a.height, a.width)
        optimizer = torch.optim.Adam(net.parameters(), lr=args.learning_rate)
        ns = None
        for i in range(a.warmup + a.runs):
            L_t, L_t1, R_t, R_t1 = (torch.rand(2, 3, a.height, a.width, generator=g, device=dev) for _ in range(4))
            if ns is None:
                ns = h.body_namespace(net, optimizer, args, L_t, L_t1, R_t, R_t1)
            ns.update(batch_idx=i, left_image_1=L_t, left_image_2=L_t1, right_image_1=R_t, right_image_2=R_t1)
            sync()
            t0 = time.perf_counter()
            with autocast():
                exec(tp["pre"], ns)  # forward + loss
            sync()
            t1 = time.perf_counter()
            exec(tp["backward"], ns)
            exec(tp["post"], ns)
            sync()
            t2 = time.perf_counter()
            if i >= a.warmup:
                times.append(t2 - t0)
                phases.append((t1 - t0, t2 - t1))
        extra = {"batch_cycles": 2, "warp_type": a.warp_type, "loss_last": float(ns["loss"].detach()),
                 "forward_and_loss_median_s": round(statistics.median(p[0] for p in phases), 4),
                 "backward_and_adam_median_s": round(statistics.median(p[1] for p in phases), 4)}
    rec = {"what": f"peer_{a.mode}", "amp": a.amp, "device": torch.cuda.get_device_name() if cuda_ok else "cpu",
           "torch_version": torch.__version__, "height": a.height, "width": a.width, "runs": a.runs,
           "warmup": a.warmup, "times_s": [round(t, 4) for t in times], "median_s": round(statistics.median(times), 4),
           "min_s": round(min(times), 4), "cuda_max_allocated_bytes": torch.cuda.max_memory_allocated() if cuda_ok
           else None, **extra}
    print(json.dumps(rec))
    return 0


if __name__ == "__main__":
    sys.exit(main())
