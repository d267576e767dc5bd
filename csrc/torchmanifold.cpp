// The extension module. It holds no Python bindings: importing the .so runs the static
// TORCH_LIBRARY registrations of every op in csrc/ops. _build_info proves how it was built.
#include <Python.h>
#include <torch/library.h>
#include <ATen/Parallel.h>

#include <string>

extern "C" {
// A do-nothing module init so `import torchmanifold._C` loads the library (and its registrations).
PyObject* PyInit__C(void) {
  static struct PyModuleDef module_def = {PyModuleDef_HEAD_INIT, "_C", nullptr, -1, nullptr};
  return PyModule_Create(&module_def);
}
}

namespace torchmanifold {

std::string build_info() {
  std::string info = "openmp=";
#ifdef _OPENMP
  info += "1";
#else
  info += "0";
#endif
  // the instruction set the kernel was compiled for (setup.py: -march, TORCHMANIFOLD_MARCH)
#if defined(__AVX2__) && defined(__FMA__)
  info += ";isa=avx2+fma";
#elif defined(__SSE2__)
  info += ";isa=sse2";
#else
  info += ";isa=generic";
#endif
  info += ";parallel=" + at::get_parallel_info();
  return info;
}

TORCH_LIBRARY_FRAGMENT(torchmanifold, m) {
  m.def("_build_info() -> str", &build_info);
}

}  // namespace torchmanifold
