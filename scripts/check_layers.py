#!/usr/bin/env python3
"""Checks that every project include follows the declared dependency order of the folders.

Each folder below may include its own files and those of the folders it lists, nothing else: an include
that climbs up (scene/ reaching into train/) or crosses (init/ into eval/) fails the check. A file belongs
to the longest folder that prefixes its path. tests/, bench/ and fuzz/ may include anything.

    python3 scripts/check_layers.py            # exit 1 and one line per offending include
"""
import pathlib
import re
import sys

# folder -> the folders it may use (its own files are always allowed). The order is the build's: a
# folder may only name folders above it in this table.
LAYERS = {
    "common": [],
    "proto": [],
    "gs_trainer/scene": ["common"],
    "gs_trainer/raster": ["common"],
    "gs_trainer/model": ["gs_trainer/raster", "gs_trainer/scene", "common"],
    "gs_trainer/init": ["gs_trainer/scene", "common"],
    "gs_trainer/eval": ["gs_trainer/raster", "common"],
    "gs_trainer/train": ["gs_trainer/model", "gs_trainer/eval", "gs_trainer/raster", "gs_trainer/scene", "common"],
    "gs_trainer/gaps": ["gs_trainer/train", "gs_trainer/model", "gs_trainer/eval", "gs_trainer/raster",
                        "gs_trainer/scene", "common"],
    # The web viewer: the page, its model formats, what it shows of a run.
    "gs_trainer/viewer": ["gs_trainer/model", "gs_trainer/scene", "common"],
    # The parts of one run: options, inputs, initial model, training, checkpoints, statistics, outputs.
    "gs_trainer/run": ["gs_trainer/gaps", "gs_trainer/train", "gs_trainer/init", "gs_trainer/eval", "gs_trainer/model",
                       "gs_trainer/scene", "common"],
    # The top level of gs_trainer puts a run together (pipeline, report, the demo scene): it uses every room.
    "gs_trainer": ["gs_trainer/run", "gs_trainer/viewer", "gs_trainer/gaps", "gs_trainer/train", "gs_trainer/init", "gs_trainer/eval",
                   "gs_trainer/model", "gs_trainer/raster", "gs_trainer/scene", "common"],
    "diffusion_worker/sdxl": ["common"],
    "diffusion_worker/depth": ["diffusion_worker/sdxl", "common"],
    "diffusion_worker/restore": ["diffusion_worker/sdxl", "common"],
    "diffusion_worker": ["diffusion_worker/sdxl", "diffusion_worker/depth", "diffusion_worker/restore", "gs_trainer/gaps",
                         "gs_trainer/scene", "common"],
    "rpc": ["proto", "gs_trainer", "gs_trainer/gaps", "gs_trainer/train", "gs_trainer/scene", "common"],
    "diffusion_worker/service": ["rpc", "diffusion_worker", "gs_trainer/gaps", "proto", "common"],
    "server": ["rpc", "proto", "diffusion_worker", "gs_trainer", "gs_trainer/gaps", "gs_trainer/train",
               "gs_trainer/init", "gs_trainer/eval", "gs_trainer/model", "gs_trainer/scene", "common"],
    "client": ["rpc", "proto", "diffusion_worker", "gs_trainer", "gs_trainer/viewer", "gs_trainer/gaps",
               "gs_trainer/train", "gs_trainer/init", "gs_trainer/eval", "gs_trainer/model", "gs_trainer/scene",
               "common"],
}
UNCHECKED = ("tests", "bench", "fuzz")
INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"|^\s*#\s*define\s+GAPS_SIMD_KERNELS\s+"([^"]+)"')
SOURCES = (".h", ".hpp", ".cpp", ".cc", ".cu", ".cuh")


def owner(path: str):
    best = None
    for folder in LAYERS:
        if (path == folder or path.startswith(folder + "/")) and (best is None or len(folder) > len(best)):
            best = folder
    return best


def check_order():
    """Every folder names only folders declared before it (no cycles by construction)."""
    seen, errors = set(), []
    for folder, uses in LAYERS.items():
        errors += [f"LAYERS: {folder} uses {u}, which is declared after it" for u in uses if u not in seen]
        seen.add(folder)
    return errors


def included_owner(include: str, root: pathlib.Path):
    # Generated protobuf headers are included as "gaps/v1/...".
    if include.startswith("gaps/v1/") or include.startswith("proto/"):
        return "proto"
    if not (root / include).exists():
        return None  # a system or third-party header spelled with quotes
    return owner(include)


def main(root: pathlib.Path) -> int:
    errors = check_order()
    checked = 0
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        if path.suffix not in SOURCES or rel.startswith(UNCHECKED) or "/build" in f"/{rel}" or rel.startswith("."):
            continue
        me = owner(rel)
        if me is None:
            errors.append(f"{rel}: in no declared folder (add it to LAYERS in scripts/check_layers.py)")
            continue
        checked += 1
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            m = INCLUDE.match(line)
            if not m:
                continue
            include = m.group(1) or m.group(2)
            other = included_owner(include, root)
            if other is None or other == me or other in LAYERS[me]:
                continue
            errors.append(f"{rel}:{number}: {me} may not include {include} ({other}); it may use: "
                          f"{', '.join(LAYERS[me]) or 'nothing'}")
    for e in errors:
        print(e)
    print(f"check_layers: {checked} files, {len(errors)} violations")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main(pathlib.Path(__file__).resolve().parent.parent))
