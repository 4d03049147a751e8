#include "springblend/runtime.h"

#include <unistd.h>

#include <cstdlib>

namespace springblend {

void ConfigureNumericalThreads(char** argv) {
  if (std::getenv("OMP_THREAD_LIMIT") != nullptr) return;  // already configured (or chosen by the user)
  setenv("OMP_THREAD_LIMIT", "1", 1);
  setenv("OPENBLAS_NUM_THREADS", "1", 0);
  execv("/proc/self/exe", argv);
  // execv only returns on failure: carry on with the libraries' defaults.
}

}  // namespace springblend
