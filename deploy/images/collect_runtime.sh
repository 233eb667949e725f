#!/usr/bin/env bash
# Build stage of the image: gathers what the runtime stage needs into DEST.
#   collect_runtime.sh DEST TORCH_SITE BINARY...
# DEST/bin: the binaries. DEST/lib: the shared libraries they load from the torch wheel's folders and the
# CUDA toolkit (for a CUDA build all of torch/lib and of the nvidia/ wheels, since LibTorch dlopens parts of
# them, e.g. cuDNN's engines and NVRTC's builtins, which ldd cannot see), and OpenCV's and libGLX (below).
# DEST/debian-packages.txt: the Debian packages that own every other library the binaries load, so the
# runtime stage installs exactly those.
set -euo pipefail
dest=$1 torch_site=$2
shift 2
mkdir -p "$dest/bin" "$dest/lib"
install -m 0755 "$@" "$dest/bin/"

linked=$(LD_LIBRARY_PATH="$torch_site/torch/lib" ldd "$@")
libraries=$(awk '$2 == "=>" && $3 ~ /^\// {print $3}' <<<"$linked" | sort -u)
if [ -z "$libraries" ]; then
  echo "collect_runtime: ldd found no shared libraries in $*" >&2
  exit 1
fi
if [ -d "$torch_site/nvidia" ] && [ -e "$torch_site/torch/lib/libtorch_cuda.so" ] && [[ $linked == *libtorch_cuda* ]]; then
  cp -a "$torch_site"/torch/lib/*.so* "$dest/lib/"
  find "$torch_site/nvidia" -name '*.so*' -path '*/lib/*' -exec cp -a {} "$dest/lib/" \;
fi

# Debian's OpenCV packages depend on libglx0 (OpenGL interop, never called here), whose dependencies are
# Mesa's drivers and LLVM (about 200 MB installed): OpenCV's libraries and libGLX are carried as files
# instead. What they load in turn (TBB, BLAS, LAPACK, X11's client library) ldd lists too, so those still
# come as packages.
carried=('libglx0' 'libopencv-*')

packages=()
for lib in $libraries; do
  case $lib in
    # The CUDA toolkit of a CUDA build is made from the same wheels (Containerfile).
    "$torch_site"/* | /usr/local/cuda*/*) cp -an "$lib" "$dest/lib/"; continue ;;
  esac
  # Debian bookworm merges /lib into /usr/lib, but dpkg knows each file under the path its package used.
  owner=$(dpkg -S "$lib" 2>/dev/null || dpkg -S "$(readlink -f "$lib")" 2>/dev/null ||
          dpkg -S "${lib#/usr}" 2>/dev/null || dpkg -S "/usr$lib" 2>/dev/null || true)
  if [ -z "$owner" ]; then
    echo "collect_runtime: no Debian package owns $lib" >&2
    exit 1
  fi
  owner=${owner%%:*}
  for pattern in "${carried[@]}"; do
    # shellcheck disable=SC2053 # the pattern is meant to match as a glob
    if [[ $owner == $pattern ]]; then
      cp -L "$lib" "$dest/lib/$(basename "$lib")"
      continue 2
    fi
  done
  packages+=("$owner")
done
printf '%s\n' "${packages[@]}" | sort -u >"$dest/debian-packages.txt"
echo "collect_runtime: $(ls "$dest/lib" | wc -l) libraries carried ($(du -sh "$dest/lib" | cut -f1)); Debian packages:"
tr '\n' ' ' <"$dest/debian-packages.txt"
echo
