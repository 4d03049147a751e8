// Stateless frames through the server (issue: the same weights give the same shape, whatever came before): a
// long Solve equals the same frames requested in chunks, on one worker and on two; an interactive session's
// settled answer equals a one-frame Solve of the same weights.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <random>

#include "integration/server_process.h"
#include "springblend/client.h"
#include "test_util.h"

namespace springblend {
namespace {

using testing::CylinderRig;
using testing::ServerProcess;
using testing::TempDir;

constexpr double kAgreement = 1e-5;  // of the bounding-box diagonal

// Frames that jump about: a sweep's frames shuffled, so a frame never follows its neighbour.
v1::SolveRequest Frames(const std::string& id, const std::vector<std::vector<double>>& weights, size_t begin,
                        size_t end) {
  v1::SolveRequest request;
  request.set_character_id(id);
  for (size_t i = begin; i < end; ++i) {
    v1::FrameRequest* f = request.add_frames();
    for (double w : weights[i]) f->add_weights(w);
  }
  return request;
}

std::vector<Points> SolveAll(Client& client, const v1::SolveRequest& request) {
  std::vector<Points> out;
  const int received = client.Solve(request, [&](const v1::SolvedFrame& frame) {
    EXPECT_EQ(frame.index(), out.size());
    EXPECT_TRUE(frame.summary().converged()) << frame.summary().message();
    out.push_back(Client::Decode(frame.positions()));
  });
  EXPECT_EQ(received, request.frames_size());
  return out;
}

std::vector<std::vector<double>> ShuffledSweep(int frames) {
  std::vector<std::vector<double>> weights;
  for (const Frame& f : SweepFrames({0.9, 0.4}, frames)) weights.push_back(f.weights);
  std::mt19937 rng(11);
  std::shuffle(weights.begin(), weights.end(), rng);
  return weights;
}

class ChunkedBake : public ::testing::TestWithParam<int> {};

TEST_P(ChunkedBake, ALongSolveEqualsTheSameFramesInThreeChunks) {
  TempDir cache;
  ServerProcess server(cache.path().string(), {"--workers", std::to_string(GetParam())});
  ASSERT_FALSE(server.address().empty()) << "the server did not start";
  Client client(ClientOptions{server.address()});
  CylinderRig cylinder;
  const v1::Character c = client.Upload(cylinder.rest, cylinder.targets);
  const auto weights = ShuffledSweep(36);
  const std::vector<Points> whole = SolveAll(client, Frames(c.id(), weights, 0, 36));
  std::vector<Points> chunked;
  for (size_t begin : {0, 12, 24}) {
    for (Points& p : SolveAll(client, Frames(c.id(), weights, begin, begin + 12))) chunked.push_back(std::move(p));
  }
  ASSERT_EQ(whole.size(), 36u);
  ASSERT_EQ(chunked.size(), 36u);
  const double diagonal = BoundingBoxDiagonal(cylinder.rest.vertices);
  for (size_t i = 0; i < whole.size(); ++i) {
    EXPECT_LE(testing::MaxDistance(whole[i], chunked[i]), kAgreement * diagonal) << "frame " << i;
  }
  // And each equals that frame alone.
  for (size_t i : {0, 17, 35}) {
    const std::vector<Points> alone = SolveAll(client, Frames(c.id(), weights, i, i + 1));
    EXPECT_LE(testing::MaxDistance(whole[i], alone[0]), kAgreement * diagonal) << "frame " << i;
  }
}

INSTANTIATE_TEST_SUITE_P(Workers, ChunkedBake, ::testing::Values(1, 2),
                         [](const ::testing::TestParamInfo<int>& workers) {
                           return std::to_string(workers.param) + "_workers";
                         });

TEST(InteractiveServer, TheSettledAnswerEqualsAOneFrameSolve) {
  TempDir cache;
  ServerProcess server(cache.path().string(), {"--workers", "2"});
  ASSERT_FALSE(server.address().empty()) << "the server did not start";
  Client client(ClientOptions{server.address()});
  CylinderRig cylinder;
  const v1::Character c = client.Upload(cylinder.rest, cylinder.targets);
  // A slider dragged up and back down, ending at (0.35, 0.2): the session's history is all over the place.
  std::vector<std::vector<double>> path;
  for (int i = 0; i <= 20; ++i) path.push_back({i / 20.0, 0.6 * i / 20.0});
  for (int i = 20; i >= 7; --i) path.push_back({i / 20.0, 0.2});
  path.push_back({0.35, 0.2});
  v1::InteractiveStart start;
  start.set_character_id(c.id());
  auto session = client.StartInteractive(start);
  for (const auto& w : path) {
    v1::FrameRequest frame;
    for (double v : w) frame.add_weights(v);
    ASSERT_TRUE(session->Send(frame));
  }
  session->Close();
  Points last;
  v1::SolvedFrame answer;
  std::uint32_t last_index = 0;
  while (session->Next(&answer)) {
    if (answer.summary().converged()) {
      last = Client::Decode(answer.positions());
      last_index = answer.index();
    }
  }
  session->Finish();
  ASSERT_EQ(last_index, path.size() - 1);
  const std::vector<Points> one = SolveAll(client, Frames(c.id(), {path.back()}, 0, 1));
  EXPECT_LE(testing::MaxDistance(last, one[0]), kAgreement * BoundingBoxDiagonal(cylinder.rest.vertices));
}

}  // namespace
}  // namespace springblend
