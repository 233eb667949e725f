#!/usr/bin/env python3
"""Fixtures for tests/lpips_test.cpp, written into --out (a fresh temporary folder).

- A torchvision VGG16 with random weights (fixed seed, weights=None, random conv biases so that
  biases matter), its state dict saved with torch.save both as zip and as legacy (pre-zip) pickle.
  The classifier is dropped except `classifier.6.bias` (keeps the files ~60 MB instead of 530 MB
  while still checking that classifier.* keys are ignored).
- Image pairs (raw float32 HxWx3, row-major) and their distances from PyPI's `lpips` package:
  LPIPS(net='vgg', version 0.1) with the v0.1 linear layers from --lin and the random trunk above.
- Broken backbones (a missing key, a wrong shape, an extra key) for the error tests.
- Tensors with non-contiguous strides, storage offsets, shared storages and assorted dtypes, saved
  as zip/legacy and with pickle protocols 2 and 4, for the checkpoint reader.
Everything is described in manifest.json.
"""
import argparse
import collections
import json
import os
import sys


def save_both_formats(obj, out, stem, protocol=2):
    import torch
    zip_name, legacy_name = f"{stem}_zip.pt", f"{stem}_legacy.pt"
    torch.save(obj, os.path.join(out, zip_name), pickle_protocol=protocol)
    torch.save(obj, os.path.join(out, legacy_name), pickle_protocol=protocol,
               _use_new_zipfile_serialization=False)
    return {"zip": zip_name, "legacy": legacy_name}


def random_vgg16_state_dict():
    import torch
    import torchvision
    torch.manual_seed(1234)
    vgg = torchvision.models.vgg16(weights=None)
    for module in vgg.features:
        if isinstance(module, torch.nn.Conv2d):
            torch.nn.init.uniform_(module.bias, -0.05, 0.05)
    state = vgg.state_dict()  # an OrderedDict with _metadata, as torchvision's files
    for key in [k for k in state if k.startswith("classifier.") and k != "classifier.6.bias"]:
        del state[key]
    return vgg, state


def reference_lpips(vgg, lin_path):
    import lpips
    import torch
    model = lpips.LPIPS(net="vgg", version="0.1", pretrained=True, pnet_rand=True,
                        model_path=lin_path, verbose=False)
    # lpips splits torchvision's `features` into slices whose modules keep their original indices.
    for part in (model.net.slice1, model.net.slice2, model.net.slice3, model.net.slice4,
                 model.net.slice5):
        for name, module in part._modules.items():
            module.load_state_dict(vgg.features[int(name)].state_dict())
    # lpips loads the linear layers with strict=False: make sure they really arrived.
    lins = torch.load(lin_path, map_location="cpu")
    for tap in range(5):
        key = f"lin{tap}.model.1.weight"
        assert torch.equal(model.state_dict()[key], lins[key]), f"{key} was not loaded"
    return model.eval()


def write_pairs(model, out):
    import numpy as np
    import torch
    rng = np.random.default_rng(99)
    pairs = []
    for index, (height, width, noise) in enumerate(
            [(64, 48, None), (37, 53, 0.05), (16, 16, None), (96, 80, 0.02)]):
        a = rng.random((height, width, 3), dtype=np.float32)
        if noise is None:
            b = rng.random((height, width, 3), dtype=np.float32)
        else:  # a perturbed copy: the small distances typical of renders vs photos
            b = np.clip(a + noise * rng.standard_normal(a.shape).astype(np.float32), 0, 1)
        names = (f"pair{index}_a.f32", f"pair{index}_b.f32")
        for name, image in zip(names, (a, b)):
            image.astype("<f4").tofile(os.path.join(out, name))
        to_nchw = lambda image: torch.from_numpy(image).permute(2, 0, 1)[None]
        with torch.no_grad():
            distance = model(to_nchw(a), to_nchw(b), normalize=True).item()
        pairs.append({"height": height, "width": width, "a": names[0], "b": names[1],
                      "distance": distance})
    return pairs


def write_bad_backbones(state, out):
    import torch
    bad = {}
    missing = collections.OrderedDict(state)
    del missing["features.28.bias"]
    wrong_shape = collections.OrderedDict(state)
    wrong_shape["features.10.weight"] = torch.zeros(256, 128, 5, 5)
    extra = collections.OrderedDict(state)
    extra["features.1.weight"] = torch.zeros(3)
    for kind, (dict_, key) in {"missing": (missing, "features.28.bias"),
                               "shape": (wrong_shape, "features.10.weight"),
                               "extra": (extra, "features.1.weight")}.items():
        name = f"vgg16_{kind}.pth"
        torch.save(dict_, os.path.join(out, name))
        bad[kind] = {"file": name, "key": key}
    return bad


def write_pickle_fixtures(out):
    import torch
    base = torch.arange(60, dtype=torch.float64).reshape(5, 12)
    views = collections.OrderedDict(
        whole=base,
        column=base[:, 3],           # stride 12, storage offset 3
        transposed=base.t(),         # strides (1, 12)
        block=base[1:4, 2:9:3],      # offset 14, strides (12, 3)
        half=torch.arange(6, dtype=torch.float16).reshape(2, 3),
        bfloat16=torch.arange(4, dtype=torch.bfloat16),
        int64=torch.arange(-3, 3, dtype=torch.int64),
        int32=torch.arange(-3, 3, dtype=torch.int32),
        uint8=torch.arange(250, 256, dtype=torch.uint8),
        bool=torch.tensor([True, False, True]),
        scalar=torch.tensor(2.5),
        empty=torch.zeros(0, 3),
        channels_last=torch.arange(24, dtype=torch.float32).reshape(1, 2, 3, 4)
        .contiguous(memory_format=torch.channels_last),
    )
    files = {f"protocol{p}_{fmt}": name
             for p in (2, 4)
             for fmt, name in save_both_formats(views, out, f"views_p{p}", protocol=p).items()}
    torch.save({"epoch": 3, "weight": torch.ones(2)}, os.path.join(out, "not_state_dict.pt"))
    files["not_state_dict"] = "not_state_dict.pt"
    return files


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", required=True, help="folder for the fixtures")
    parser.add_argument("--lin", required=True, help="LPIPS v0.1 vgg.pth (linear layers)")
    args = parser.parse_args()
    try:
        import lpips  # noqa: F401
        import numpy  # noqa: F401
        import torch  # noqa: F401
        import torchvision  # noqa: F401
    except ImportError as error:
        # 77: the C++ test reports a skip naming what is missing (e.g. on a GPU host without lpips).
        print(f"lpips_reference.py: {error}. This test needs torch, torchvision, numpy and "
              f"lpips==0.1.4 in {sys.executable}; scripts/setup.sh installs them.", file=sys.stderr)
        sys.exit(77)
    vgg, state = random_vgg16_state_dict()
    manifest = {
        "backbones": save_both_formats(state, args.out, "vgg16_random"),
        "pairs": write_pairs(reference_lpips(vgg, args.lin), args.out),
        "bad_backbones": write_bad_backbones(state, args.out),
        "pickles": write_pickle_fixtures(args.out),
    }
    with open(os.path.join(args.out, "manifest.json"), "w") as f:
        json.dump(manifest, f, indent=1)


if __name__ == "__main__":
    main()
