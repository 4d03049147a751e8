#include <gtest/gtest.h>

#include "springblend/runtime.h"

int main(int argc, char** argv) {
  springblend::ConfigureNumericalThreads(argv);
  testing::InitGoogleTest(&argc, argv);
  return RUN_ALL_TESTS();
}
