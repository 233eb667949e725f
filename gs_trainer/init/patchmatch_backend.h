#pragma once
// PatchMatch's steps over one view, each patchmatch_math.h's per-pixel function applied to every pixel (or to
// one colour of the checkerboard): cpu/ loops on the host, cuda/ launches a kernel per step. patchmatch.cpp
// picks the table by the images' device and runs the schedule.
#include "gs_trainer/init/patchmatch_math.h"

namespace gaps::pm {

struct Backend {
  void (*init)(const Problem& p);                               // random hypotheses and their costs
  void (*update)(const Problem& p, int colour, int iteration);  // one colour's half of a sweep
  void (*rescore)(const Problem& p);                            // costs of the kept hypotheses, anew
  void (*filter)(const Problem& p);                             // depth 0 where the estimate fails
};

extern const Backend kCpuBackend;
#if defined(GAPS_CUDA_KERNELS)
// Runs on the current CUDA device and stream; the Problem's pointers are device memory.
extern const Backend kCudaBackend;
#endif

}  // namespace gaps::pm
