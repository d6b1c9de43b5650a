#!/usr/bin/env python3
"""The online GRU step of blapose against ONNX Runtime and OpenVINO, side by side.

Why: a frames/s number means little without a peer measured on the same
machine in the same minute. This script exports the online model's step (the
network blapose's `gru-step` times: Linear(34->256)+ReLU, two GRUs of 512
units over the embedding, sigmoid, Linear(1024->16) with the left/right
pair averaging folded in) to ONNX from the safetensors weights, with the
`onnx` helper API (no PyTorch), then times, interleaved round by round:

* blapose `gru-step` (f16 weights and bf16; the binary must be built),
* ONNX Runtime (CPU execution provider, f32),
* OpenVINO (CPU, INFERENCE_PRECISION_HINT f32 and bf16),

at each batch size with the same thread count, and prints a table of the
medians and every peer's ratio to ours. Each peer runs the graph in two
forms, the ONNX `GRU` operator (what a PyTorch export gives) and the same
cell spelled out as MatMul/Sigmoid/Tanh, and is credited with its faster one.

Run from a virtual environment (see bench/README.md):

    python3 -m venv .venv-peers && .venv-peers/bin/pip install onnx onnxruntime openvino numpy safetensors
    cargo build --release -p blapose-bench --bin gru-step
    .venv-peers/bin/python bench/peers/gru_step_peers.py --threads 2 --batches 1,64,256

The peers run the step as a stateless graph (the states are inputs and
outputs, fed back each step), as a serving loop would.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
HIDDEN = 512
EMBED = 256
INPUT = 34
OUT = 16
# (right, left) bone pairs averaged by the model (blapose_core::skeleton)
PAIRS = [(0, 3), (1, 4), (2, 5), (13, 10), (14, 11), (15, 12)]


def load_weights(path: Path) -> dict[str, np.ndarray]:
    from safetensors.numpy import load_file

    return {k: v.astype(np.float32) for k, v in load_file(str(path)).items()}


def averaging_matrix() -> np.ndarray:
    s = np.eye(OUT, dtype=np.float32)
    for r, l in PAIRS:
        s[r, r] = s[l, l] = s[r, l] = s[l, r] = 0.5
    return s


def build_model(w: dict[str, np.ndarray], form: str):
    """The step as an ONNX model: inputs x [B,34], h0, h1 [B,512]; outputs
    y [B,16], h0n, h1n [B,512]. `form` is "gru" (ONNX GRU operator) or
    "cell" (MatMul/Sigmoid/Tanh)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    inits = []
    nodes = []

    def const(name: str, value: np.ndarray) -> str:
        inits.append(numpy_helper.from_array(value.astype(np.float32), name))
        return name

    def const_i64(name: str, value: list[int]) -> str:
        inits.append(numpy_helper.from_array(np.array(value, dtype=np.int64), name))
        return name

    def node(op: str, inputs: list[str], out: str, **attrs) -> str:
        nodes.append(helper.make_node(op, inputs, [out], **attrs))
        return out

    # embedding
    e = node("MatMul", ["x", const("embed_wt", w["expand_conv.weight"].T)], "e_mm")
    e = node("Add", [e, const("embed_b", w["expand_conv.bias"])], "e_add")
    e = node("Relu", [e], "e")
    states = []
    for g in range(2):
        p = f"gru.{g}"
        w_ih, w_hh = w[f"{p}.weight_ih_l0"], w[f"{p}.weight_hh_l0"]
        b_ih, b_hh = w[f"{p}.bias_ih_l0"], w[f"{p}.bias_hh_l0"]
        h = f"h{g}"
        if form == "gru":
            # ONNX gate order z, r, h; PyTorch's r, z, n
            def zrh(m: np.ndarray) -> np.ndarray:
                r, z, n = np.split(m, 3, axis=0)
                return np.concatenate([z, r, n], axis=0)

            wt = const(f"W{g}", zrh(w_ih)[None])
            rt = const(f"R{g}", zrh(w_hh)[None])
            bt = const(f"B{g}", np.concatenate([zrh(b_ih), zrh(b_hh)])[None])
            x3 = node("Unsqueeze", [e, const_i64(f"ax0_{g}", [0])], f"x3_{g}")
            h3 = node("Unsqueeze", [h, f"ax0_{g}"], f"h3_{g}")
            nodes.append(
                helper.make_node(
                    "GRU",
                    [x3, wt, rt, bt, "", h3],
                    ["", f"hn3_{g}"],
                    hidden_size=HIDDEN,
                    linear_before_reset=1,
                )
            )
            hn = node("Squeeze", [f"hn3_{g}", f"ax0_{g}"], f"h{g}n")
        else:
            gi = node("MatMul", [e, const(f"wih{g}", w_ih.T)], f"gi_mm{g}")
            gi = node("Add", [gi, const(f"bih{g}", b_ih)], f"gi{g}")
            gh = node("MatMul", [h, const(f"whh{g}", w_hh.T)], f"gh_mm{g}")
            gh = node("Add", [gh, const(f"bhh{g}", b_hh)], f"gh{g}")
            split = helper.make_node("Split", [gi], [f"ir{g}", f"iz{g}", f"in{g}"], axis=1, num_outputs=3)
            split2 = helper.make_node("Split", [gh], [f"hr{g}", f"hz{g}", f"hn_{g}"], axis=1, num_outputs=3)
            nodes.extend([split, split2])
            r = node("Sigmoid", [node("Add", [f"ir{g}", f"hr{g}"], f"rs{g}")], f"r{g}")
            z = node("Sigmoid", [node("Add", [f"iz{g}", f"hz{g}"], f"zs{g}")], f"z{g}")
            n = node("Tanh", [node("Add", [f"in{g}", node("Mul", [r, f"hn_{g}"], f"rn{g}")], f"ns{g}")], f"n{g}")
            # h' = n + z (h - n)
            d = node("Sub", [h, n], f"d{g}")
            hn = node("Add", [n, node("Mul", [z, d], f"zd{g}")], f"h{g}n")
        states.append(hn)
    feat = node("Concat", states, "feat", axis=1)
    s = node("Sigmoid", [feat], "s")
    fc = (averaging_matrix() @ w["fc.weight"]).T  # [1024, 16]
    node("MatMul", [s, const("fc", fc)], "y")
    batch = "B"
    graph = helper.make_graph(
        nodes,
        f"blapose_gru_step_{form}",
        [
            helper.make_tensor_value_info("x", TensorProto.FLOAT, [batch, INPUT]),
            helper.make_tensor_value_info("h0", TensorProto.FLOAT, [batch, HIDDEN]),
            helper.make_tensor_value_info("h1", TensorProto.FLOAT, [batch, HIDDEN]),
        ],
        [
            helper.make_tensor_value_info("y", TensorProto.FLOAT, [batch, OUT]),
            helper.make_tensor_value_info("h0n", TensorProto.FLOAT, [batch, HIDDEN]),
            helper.make_tensor_value_info("h1n", TensorProto.FLOAT, [batch, HIDDEN]),
        ],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    onnx.checker.check_model(model)
    return model


def reference_step(w, x, h0, h1):
    """numpy f32 step, to check the exported graphs."""

    def sig(v):
        return 1.0 / (1.0 + np.exp(-v))

    e = np.maximum(x @ w["expand_conv.weight"].T + w["expand_conv.bias"], 0)
    out = []
    for g, h in enumerate((h0, h1)):
        p = f"gru.{g}"
        gi = e @ w[f"{p}.weight_ih_l0"].T + w[f"{p}.bias_ih_l0"]
        gh = h @ w[f"{p}.weight_hh_l0"].T + w[f"{p}.bias_hh_l0"]
        ir, iz, i_n = np.split(gi, 3, axis=1)
        hr, hz, h_n = np.split(gh, 3, axis=1)
        r, z = sig(ir + hr), sig(iz + hz)
        n = np.tanh(i_n + r * h_n)
        out.append(n + z * (h - n))
    y = sig(np.concatenate(out, axis=1)) @ (averaging_matrix() @ w["fc.weight"]).T
    return y, out[0], out[1]


class Peer:
    """One runtime configuration: `run(steps)` advances its states `steps`
    frames and returns the seconds taken."""

    def __init__(self, name, make_session, batch, seed=1):
        self.name = name
        rng = np.random.default_rng(seed)
        self.frames = rng.uniform(-1, 1, (64, batch, INPUT)).astype(np.float32)
        self.h0 = np.zeros((batch, HIDDEN), np.float32)
        self.h1 = np.zeros((batch, HIDDEN), np.float32)
        self.step = make_session()

    def run(self, steps: int) -> float:
        start = time.perf_counter()
        h0, h1 = self.h0, self.h1
        for t in range(steps):
            _, h0, h1 = self.step(self.frames[t % 64], h0, h1)
        secs = time.perf_counter() - start
        self.h0, self.h1 = np.zeros_like(h0), np.zeros_like(h1)
        return secs


def ort_session(model_bytes: bytes, threads: int):
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    sess = ort.InferenceSession(model_bytes, opts, providers=["CPUExecutionProvider"])

    def step(x, h0, h1):
        return sess.run(None, {"x": x, "h0": h0, "h1": h1})

    return step


def ov_session(model_bytes: bytes, threads: int, precision: str):
    import openvino as ov

    core = ov.Core()
    model = core.read_model(model=model_bytes, weights=b"")
    compiled = core.compile_model(
        model,
        "CPU",
        {
            "INFERENCE_PRECISION_HINT": precision,
            "INFERENCE_NUM_THREADS": threads,
            "NUM_STREAMS": 1,
            "PERFORMANCE_HINT": "LATENCY",
        },
    )
    req = compiled.create_infer_request()
    outs = [compiled.output(i) for i in range(3)]

    def step(x, h0, h1):
        r = req.infer({"x": x, "h0": h0, "h1": h1})
        return r[outs[0]], r[outs[1]], r[outs[2]]

    return step


def ours(binary: Path, batch: int, threads: int, steps: int, precision: str) -> float | None:
    cmd = [
        str(binary),
        "--batch", str(batch),
        "--threads", str(threads),
        "--steps", str(steps),
        "--precision", precision,
        "--repeats", "1",
    ]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:
        print(f"  {precision}: gru-step failed: {e}", file=sys.stderr)
        return None
    m = re.search(r"frames_per_second=(\d+)", out)
    return float(m.group(1)) if m else None


def cpu_name() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def cpu_flags() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("flags"):
                flags = line.split(":", 1)[1].split()
                keep = [f for f in flags if f.startswith(("avx512f", "avx512_bf16", "avx512_fp16", "amx", "avx2"))]
                return " ".join(sorted(keep))
    except OSError:
        pass
    return ""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", default=str(REPO / "models" / "bone_length_gru.safetensors"))
    ap.add_argument("--gru-step", default=str(REPO / "target" / "release" / "gru-step"),
                    help="the blapose gru-step binary (default: target/release/gru-step; "
                    "CARGO_TARGET_DIR is honoured)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--batches", default="1,64,256")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds; medians are reported")
    ap.add_argument("--seconds", type=float, default=1.0, help="approximate length of one timed run")
    ap.add_argument("--ours", default="f16,bf16", help="blapose precisions to run")
    ap.add_argument("--json", help="also write the results here")
    args = ap.parse_args()

    binary = Path(args.gru_step)
    if "CARGO_TARGET_DIR" in os.environ and args.gru_step == ap.get_default("gru_step"):
        binary = Path(os.environ["CARGO_TARGET_DIR"]) / "release" / "gru-step"
    if not binary.exists():
        print(f"{binary} not found: cargo build --release -p blapose-bench --bin gru-step", file=sys.stderr)
        return 2

    w = load_weights(Path(args.weights))
    models = {form: build_model(w, form).SerializeToString() for form in ("gru", "cell")}

    # the exported graphs compute the same step as numpy
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (3, INPUT)).astype(np.float32)
    h0 = rng.uniform(-1, 1, (3, HIDDEN)).astype(np.float32)
    h1 = rng.uniform(-1, 1, (3, HIDDEN)).astype(np.float32)
    want = reference_step(w, x, h0, h1)
    for form, mb in models.items():
        got = ort_session(mb, 1)(x, h0, h1)
        err = max(float(np.abs(a - b).max()) for a, b in zip(got, want))
        if err > 1e-4:
            print(f"exported {form} graph disagrees with numpy: {err:.2e}", file=sys.stderr)
            return 1

    print(f"CPU: {cpu_name()}; flags: {cpu_flags()}; {os.cpu_count()} logical CPUs; "
          f"threads {args.threads}; onnxruntime and openvino from pip; weights {Path(args.weights).name}")
    results = []
    for batch in [int(b) for b in args.batches.split(",")]:
        peers = []
        for form, mb in models.items():
            peers.append((f"ORT f32 [{form}]", lambda mb=mb: ort_session(mb, args.threads)))
            peers.append((f"OV f32 [{form}]", lambda mb=mb: ov_session(mb, args.threads, "f32")))
            peers.append((f"OV bf16 [{form}]", lambda mb=mb: ov_session(mb, args.threads, "bf16")))
        runners = [Peer(name, make, batch) for name, make in peers]
        # steps per timed run from a short calibration, per runner
        steps = {}
        for r in runners:
            r.run(3)
            t = r.run(10) / 10
            steps[r.name] = max(5, int(args.seconds / max(t, 1e-6)))
        ours_steps = {}
        for prec in args.ours.split(","):
            fps = ours(binary, batch, args.threads, 50, prec)
            if fps:
                ours_steps[prec] = max(20, int(args.seconds * fps / batch))
        rates: dict[str, list[float]] = {}
        for _ in range(args.rounds):
            for prec, n in ours_steps.items():
                fps = ours(binary, batch, args.threads, n, prec)
                if fps:
                    rates.setdefault(f"blapose {prec}", []).append(fps)
            for r in runners:
                secs = r.run(steps[r.name])
                rates.setdefault(r.name, []).append(steps[r.name] * batch / secs)
        med = {k: statistics.median(v) for k, v in rates.items()}
        # each peer configuration credited with its faster graph form
        best = {}
        for k, v in med.items():
            base = k.split(" [")[0]
            if base not in best or v > best[base][0]:
                best[base] = (v, k)
        results.append({"batch": batch, "threads": args.threads, "medians": med, "best": best})
        print(f"\nbatch {batch}, {args.threads} threads (medians of {args.rounds} interleaved rounds)")
        for k in sorted(med, key=lambda k: -med[k]):
            print(f"  {k:<22} {med[k]:>10,.0f} frames/s")

    print("\n| batch | threads | " + " | ".join(["blapose " + p for p in args.ours.split(",")])
          + " | ORT f32 | OV f32 | OV bf16 | ours best / OV bf16 | ours best / ORT f32 |")
    print("|---:|---:|" + "---:|" * (len(args.ours.split(",")) + 5))
    for r in results:
        b = r["best"]
        ours_v = [b.get("blapose " + p, (float("nan"),))[0] for p in args.ours.split(",")]
        top = max(v for v in ours_v if v == v) if any(v == v for v in ours_v) else float("nan")

        def peer(name):
            return b.get(name, (float("nan"), ""))

        cols = [f"{v:,.0f}" for v in ours_v]
        cols += [f"{peer(n)[0]:,.0f} ({peer(n)[1].split('[')[-1].rstrip(']')})" for n in ("ORT f32", "OV f32", "OV bf16")]
        cols += [f"{top / peer('OV bf16')[0]:.2f}x", f"{top / peer('ORT f32')[0]:.2f}x"]
        print(f"| {r['batch']} | {r['threads']} | " + " | ".join(cols) + " |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"cpu": cpu_name(), "flags": cpu_flags(), "results": results}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
