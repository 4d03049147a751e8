// The conversion layer's last check on an answer: positions that are not finite as float32 (finite doubles
// beyond 3.4e38 included) are never sent as OK, but fail their frame with INTERNAL naming it. What requests
// hold, as the memory budget counts it.
#include "convert.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "memory_budget.h"
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

// The request memory budget: a reservation beyond it says what was asked and what is free, gives back what it
// shrinks by and all it holds when it goes.
TEST(Reservation, RefusesBeyondTheBudgetWithTheFigures) {
  MemoryBudget budget(1000);
  {
    Reservation first(&budget);
    first.Grow(600);
    Reservation second(&budget);
    EXPECT_FALSE(second.TryGrow(500));
    EXPECT_EQ(budget.used(), 600);
    try {
      second.Grow(500);
      ADD_FAILURE() << "500 more bytes fitted beside 600 in 1000";
    } catch (const LimitError& e) {
      EXPECT_EQ(ToStatus(e).error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
      EXPECT_THAT(e.what(), HasSubstr("needs 500 bytes"));
      EXPECT_THAT(e.what(), HasSubstr("400 bytes are free"));
      EXPECT_THAT(e.what(), HasSubstr("--request-memory-mb"));
    }
    first.Shrink(200);
    EXPECT_EQ(budget.used(), 400);
    first.Shrink(10'000);  // never more than it holds
    EXPECT_EQ(budget.used(), 0);
    second.Grow(500);
    EXPECT_EQ(budget.used(), 500);
  }
  EXPECT_EQ(budget.used(), 0);
}

// A parsed Solve request of pins holds more than its bytes on the wire (each pin and its position are messages
// of their own), and its converted frames are counted from the same counts.
TEST(RequestBytes, CountsMoreThanTheWireForPins) {
  v1::SolveRequest request;
  request.set_character_id(std::string(64, 'a'));
  for (int f = 0; f < 100; ++f) {
    v1::FrameRequest* frame = request.add_frames();
    frame->add_weights(0.5);
    for (int p = 0; p < 50; ++p) {
      v1::Pin* pin = frame->add_pins();
      pin->set_vertex(static_cast<std::uint32_t>(p));
      pin->mutable_position()->set_x(1);
      pin->mutable_position()->set_y(2);
      pin->mutable_position()->set_z(3);
    }
  }
  EXPECT_GT(RequestBytes(request), 2 * static_cast<std::int64_t>(request.ByteSizeLong()));
  Frame frame;
  frame.weights.assign(1, 0.5);
  frame.pins.assign(50, Pin{});
  EXPECT_EQ(FrameBytes(request.frames(0)), FrameBytes(frame));
  EXPECT_GE(FrameBytes(frame), static_cast<std::int64_t>(50 * sizeof(Pin)));
}

}  // namespace
}  // namespace springblend::server
