# LibTorch from PyPI's torch wheel. Provides the target gaps::torch.
# With CUDA the wheel's own CMake config is used (it needs the CUDA toolkit); without, only the
# CPU libraries are linked, so a machine without nvcc still builds.
# The tests' Python (GAPS_PYTHON) is looked up even when Torch_DIR is given, so the scripts the tests run have
# an interpreter on every build.
find_program(GAPS_PYTHON NAMES python3 python HINTS $ENV{HOME}/.cache/gaps/venv/bin NO_DEFAULT_PATH)
if(NOT GAPS_PYTHON)
  find_program(GAPS_PYTHON NAMES python3 python)
endif()
if(NOT Torch_DIR AND NOT DEFINED ENV{Torch_DIR})
  execute_process(COMMAND ${GAPS_PYTHON} -c "import torch, os; print(os.path.dirname(torch.__file__))"
                  OUTPUT_VARIABLE GAPS_TORCH_ROOT OUTPUT_STRIP_TRAILING_WHITESPACE RESULT_VARIABLE _rc ERROR_QUIET)
  if(NOT _rc EQUAL 0 OR NOT GAPS_TORCH_ROOT)
    message(FATAL_ERROR "LibTorch not found: run scripts/setup.sh (installs torch==2.11.0 under ~/.cache/gaps/venv) or pass -DTorch_DIR=...")
  endif()
  set(Torch_DIR "${GAPS_TORCH_ROOT}/share/cmake/Torch")
endif()
get_filename_component(GAPS_TORCH_ROOT "${Torch_DIR}/../../.." ABSOLUTE)

add_library(gaps_torch INTERFACE)
add_library(gaps::torch ALIAS gaps_torch)
if(GAPS_WITH_CUDA)
  find_package(Torch REQUIRED)
  target_link_libraries(gaps_torch INTERFACE ${TORCH_LIBRARIES})
else()
  find_library(GAPS_TORCH_CPU torch_cpu PATHS ${GAPS_TORCH_ROOT}/lib NO_DEFAULT_PATH REQUIRED)
  find_library(GAPS_C10 c10 PATHS ${GAPS_TORCH_ROOT}/lib NO_DEFAULT_PATH REQUIRED)
  target_include_directories(gaps_torch SYSTEM INTERFACE
    ${GAPS_TORCH_ROOT}/include ${GAPS_TORCH_ROOT}/include/torch/csrc/api/include)
  target_link_libraries(gaps_torch INTERFACE ${GAPS_TORCH_CPU} ${GAPS_C10})
endif()
message(STATUS "gaps: LibTorch at ${GAPS_TORCH_ROOT}")
