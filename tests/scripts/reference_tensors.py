"""How the fixture scripts store their reference outputs: one safetensors file per reference, floating-point
tensors as float32 (what the C++ tests compare in), integer ones (token ids, timesteps) as they are."""
import os

from safetensors.torch import save_file


def reference_saver(folder):
    """save(name, tensors), writing folder/name.safetensors."""
    def save(name, tensors):
        save_file({k: v.detach().contiguous().float() if v.is_floating_point() else v.contiguous()
                   for k, v in tensors.items()}, os.path.join(folder, name + ".safetensors"))
    return save
