"""What the weight converters (lpips_weights.py, realesrgan_weights.py) share: the safetensors bytes they write
and the pinned-output discipline (a file already there is verified by its sha256; a new one is written only when
its bytes are the pinned ones, atomically)."""
import hashlib
import json
import os
import struct


class WeightsError(Exception):
    pass


def sha256_of(data):
    return hashlib.sha256(data).hexdigest()


def safetensors_bytes(tensors, metadata):
    """(name, numpy array) pairs as float32 safetensors, in the order given."""
    header, offset = {"__metadata__": metadata}, 0
    for name, array in tensors:
        size = array.size * 4
        header[name] = {"dtype": "F32", "shape": list(array.shape), "data_offsets": [offset, offset + size]}
        offset += size
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # the data starts 8-byte aligned
    body = b"".join(array.astype("<f4").tobytes() for _, array in tensors)
    return struct.pack("<Q", len(text)) + text + body


def make_pinned(output, expected_sha256, convert, tag):
    """Verifies `output` if it is there, else writes convert()'s bytes to it if their sha256 is the pinned one."""
    if output.exists():
        actual = sha256_of(output.read_bytes())
        if actual == expected_sha256:
            print(f"{tag}: {output} verified")
            return
        print(f"{tag}: {output} has sha256 {actual}, not {expected_sha256}: making it again")
    data = convert()
    if sha256_of(data) != expected_sha256:
        raise WeightsError(f"the converted weights have sha256 {sha256_of(data)}, not the pinned {expected_sha256}")
    output.parent.mkdir(parents=True, exist_ok=True)
    partial = output.with_name(f"{output.name}.{os.getpid()}.partial")
    partial.write_bytes(data)
    os.replace(partial, output)
    print(f"{tag}: wrote {output} ({len(data) / 1e6:.1f} MB, sha256 {expected_sha256[:12]}…)")
