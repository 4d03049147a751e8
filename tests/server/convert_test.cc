// The conversion layer's last check on an answer: positions that are not finite as float32 (finite doubles
// beyond 3.4e38 included) are never sent as OK, but fail their frame with INTERNAL naming it.
#include "convert.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "springblend/error.h"
#include "status.h"

namespace springblend::server {
namespace {

using ::testing::HasSubstr;

TEST(CheckSolved, PositionsBeyondFloat32FailTheirFrameWithInternal) {
  Points positions = Points::Zero(4, 3);
  EXPECT_NO_THROW(CheckSolved(positions, 0));
  positions(2, 1) = 3e38;  // finite as float32
  EXPECT_NO_THROW(CheckSolved(positions, 0));
  for (const double bad : {1e39, -1e300, std::numeric_limits<double>::quiet_NaN()}) {
    positions(2, 1) = bad;
    try {
      CheckSolved(positions, 7);
      ADD_FAILURE() << bad << " was accepted";
    } catch (const Error& e) {
      const grpc::Status status = ToStatus(e);
      EXPECT_EQ(status.error_code(), grpc::StatusCode::INTERNAL) << bad;
      EXPECT_THAT(status.error_message(), HasSubstr("frame 7")) << bad;
    }
  }
}

}  // namespace
}  // namespace springblend::server
