#!/usr/bin/env bash
# Installs PyPI's gsplat (the pure-Python wheel whose CUDA extension compiles at first import) into a
# private folder for bench/rasterizer_compare.py, on a machine without network access: the wheel and its
# dependencies are taken from WHEEL_DIR (fetch them elsewhere with `pip download`; see bench/README.md).
#
# Build time: gsplat instantiates its rasterization kernels for 19 channel counts (1 ... 513) and compiles
# 2DGS and 3DGUT kernels too; that JIT build does not finish in a reasonable time even on 16 cores. The
# comparison renders 4 channels (RGB + expected depth, like gaps's colour + depth), so the channel lists
# of the kernel instantiations and of their dispatch switches are cut to 1-5 channels, consistently, which
# leaves every kernel's code as published. Nothing else is changed.
#   bash bench/gsplat_setup.sh WHEEL_DIR TARGET_DIR
set -euo pipefail
wheels=$1
target=$2
python3 -m pip install -q --no-index --no-deps --target "$target" "$wheels"/gsplat-*.whl "$wheels"/jaxtyping-*.whl \
  "$wheels"/wadler_lindig-*.whl "$wheels"/rich-*.whl "$wheels"/markdown_it_py-*.whl "$wheels"/mdurl-*.whl \
  "$wheels"/pygments-*.whl
csrc="$target/gsplat/cuda/csrc"
[ -d "$csrc" ] || { echo "gsplat_setup: $csrc not found (not the expected gsplat wheel layout)" >&2; exit 1; }
python3 - "$csrc" <<'PY'
import pathlib, re, sys
keep = {1, 2, 3, 4, 5}
pattern = re.compile(r"^\s*(__INS__|__LAUNCH_KERNEL__)\((\d+)\)\s*$")
cut = 0
for path in pathlib.Path(sys.argv[1]).glob("*.c*"):
    lines = path.read_text().splitlines(keepends=True)
    kept = [l for l in lines if not (pattern.match(l) and int(pattern.match(l).group(2)) not in keep)]
    cut += len(lines) - len(kept)
    path.write_text("".join(kept))
print(f"gsplat_setup: removed {cut} channel instantiations/dispatch cases (kept {sorted(keep)})")
PY
