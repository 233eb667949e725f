#pragma once
// A CUDA stream of the pool for work that must not run on the caller's stream: CUDA-graph captures, which
// need a stream of their own (the UNet's graphs, the LoRA training's), and the LoRA training's replays.
#if defined(GAPS_CUDA_KERNELS)
#include <ATen/cuda/CUDAEvent.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

namespace gaps::sdxl {

// While one lives, the device's current stream is a stream of the pool that first waited for the caller's
// stream (so it reads what the caller wrote); when it ends, whatever way its scope is left, errors included,
// the caller's stream waits for the work issued meanwhile and is current again.
class SideStream {
 public:
  explicit SideStream(c10::DeviceIndex device)
      : caller_(c10::cuda::getCurrentCUDAStream(device)),
        stream_(c10::cuda::getStreamFromPool(/*isHighPriority=*/false, device)),
        guard_(stream_) {
    at::cuda::CUDAEvent ready;
    ready.record(caller_);
    ready.block(stream_);
  }
  ~SideStream() {
    at::cuda::CUDAEvent done;
    done.record(stream_);
    done.block(caller_);
  }
  SideStream(const SideStream&) = delete;
  SideStream& operator=(const SideStream&) = delete;

  const c10::cuda::CUDAStream& stream() const { return stream_; }

 private:
  c10::cuda::CUDAStream caller_;
  c10::cuda::CUDAStream stream_;
  c10::cuda::CUDAStreamGuard guard_;  // restores the caller's stream after the destructor's join
};

}  // namespace gaps::sdxl
#endif
