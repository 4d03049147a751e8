// Captured takes (client/cli/take.h, issue 59): reading Live Link Face CSVs, their timing, matching shape names to a
// rig's targets (conventions, symmetric shapes, maps), lost-tracking rows and bad takes named by line and column.
// Takes other than the bundled excerpt are generated here: other rates, lengths and long stretches of lost tracking.
#include "take.h"

#include <fmt/format.h>
#include <gtest/gtest.h>

#include <cmath>
#include <string>
#include <vector>

#include "springblend/error.h"
#include "test_util.h"

namespace springblend::cli {
namespace {

using springblend::testing::DataPath;

// The ICT-FaceKit expressions of ../shared/meshes/face6706, as the rig names them.
const std::vector<std::string> kIctTargets = {
    "browDown_L", "browDown_R", "browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R", "cheekPuff_L",
    "cheekPuff_R", "cheekRaiser_L", "cheekRaiser_R", "cheekSquint_L", "cheekSquint_R", "eyeBlink_L", "eyeBlink_R",
    "eyeLookDown_L", "eyeLookDown_R", "eyeLookIn_L", "eyeLookIn_R", "eyeLookOut_L", "eyeLookOut_R", "eyeLookUp_L",
    "eyeLookUp_R", "eyeSquint_L", "eyeSquint_R", "eyeWide_L", "eyeWide_R", "jawForward", "jawLeft", "jawOpen",
    "jawRight", "mouthClose", "mouthDimple_L", "mouthDimple_R", "mouthFrown_L", "mouthFrown_R", "mouthFunnel",
    "mouthLeft", "mouthLowerDown_L", "mouthLowerDown_R", "mouthPress_L", "mouthPress_R", "mouthPucker", "mouthRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthSmile_L", "mouthSmile_R",
    "mouthStretch_L", "mouthStretch_R", "mouthUpperUp_L", "mouthUpperUp_R", "noseSneer_L", "noseSneer_R"};

int Index(const std::vector<std::string>& names, const std::string& name) {
  for (size_t i = 0; i < names.size(); ++i) {
    if (names[i] == name) return static_cast<int>(i);
  }
  ADD_FAILURE() << name << " not found";
  return -1;
}

// The message of the Error that reading `text` as a take throws.
std::string TakeError(const std::string& text) {
  try {
    ParseTake(text, "bad.csv");
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidInput);
    return e.what();
  }
  ADD_FAILURE() << "no error for:\n" << text;
  return "";
}

// A take with a Timecode column counting `rate` frames per second, stepping by `step` from hh:mm:ss:ff, one value
// per row for the shapes; rows in `lost` are lost-tracking rows.
std::string MakeTake(int rows, int rate, int step, long start_seconds, int start_frame, const std::vector<bool>& lost = {}) {
  std::string text = "Timecode,BlendShapeCount,JawOpen,BrowInnerUp,HeadYaw\n";
  long frame = start_seconds * rate + start_frame;
  for (int r = 0; r < rows; ++r, frame += step) {
    const long day = frame / rate % 86400;
    const std::string code =
        fmt::format("{:02d}:{:02d}:{:02d}:{:02d}.{:03d}", day / 3600, day / 60 % 60, day % 60, frame % rate, r % 1000);
    if (r < static_cast<int>(lost.size()) && lost[r]) {
      text += code + ",0\n";
    } else {
      text += fmt::format("{},61,{},{},0.1\n", code, (r % 10) / 10.0, 1.0 - (r % 10) / 10.0);
    }
  }
  return text;
}

TEST(TakeTest, ReadsTheBundledExcerpt) {
  const Take take = ReadTake(DataPath("take/alex_rom_4_excerpt.csv"));
  EXPECT_EQ(take.rows.size(), 40u);
  ASSERT_EQ(take.shapes.size(), 52u);
  EXPECT_EQ(take.shapes.front(), "EyeBlinkLeft");
  EXPECT_EQ(take.shapes.back(), "TongueOut");
  EXPECT_EQ(take.other_columns.size(), 9u);  // HeadYaw ... RightEyeRoll
  EXPECT_EQ(take.rows.front().line, 2);
  EXPECT_EQ(take.rows.front().timecode, "16:56:29:40.140");
  EXPECT_EQ(take.lost_rows(), 0);
  // Live Link Face: the timecode counts 60 per second and steps by 2, a 30 fps take.
  EXPECT_TRUE(take.timing.known);
  EXPECT_FALSE(take.timing.rate_assumed);
  EXPECT_EQ(take.timing.timecode_rate, 60);
  EXPECT_EQ(take.timing.step, 2);
  EXPECT_EQ(take.timing.frame_rate, 30.0);
  EXPECT_EQ(take.timing.start_frame, ((16 * 3600 + 56 * 60 + 29) * 60 + 40) / 2.0);
}

TEST(TakeTest, MatchesArkitNamesToIctTargets) {
  const Take take = ReadTake(DataPath("take/alex_rom_4_excerpt.csv"));
  const TakeFrames frames = MatchTake(take, kIctTargets);
  ASSERT_EQ(frames.weights.size(), 40u);
  const TakeRow& row = take.rows[7];
  const std::vector<double>& w = frames.weights[7];
  const auto column = [&](const std::string& shape) { return row.values[Index(take.shapes, shape)]; };
  EXPECT_EQ(w[Index(kIctTargets, "jawOpen")], column("JawOpen"));
  EXPECT_EQ(w[Index(kIctTargets, "jawLeft")], column("JawLeft"));  // a direction, not a side
  EXPECT_EQ(w[Index(kIctTargets, "mouthLeft")], column("MouthLeft"));
  EXPECT_EQ(w[Index(kIctTargets, "eyeLookIn_L")], column("EyeLookInLeft"));
  EXPECT_EQ(w[Index(kIctTargets, "mouthSmile_R")], column("MouthSmileRight"));
  // Symmetric ARKit shapes drive both halves.
  EXPECT_EQ(w[Index(kIctTargets, "browInnerUp_L")], column("BrowInnerUp"));
  EXPECT_EQ(w[Index(kIctTargets, "browInnerUp_R")], column("BrowInnerUp"));
  EXPECT_EQ(w[Index(kIctTargets, "cheekPuff_R")], column("CheekPuff"));
  const TakeReport& report = frames.report;
  EXPECT_EQ(report.unmatched_shapes, std::vector<std::string>{"TongueOut"});
  EXPECT_EQ(report.undriven_targets, (std::vector<std::string>{"cheekRaiser_L", "cheekRaiser_R"}));
  EXPECT_TRUE(report.ambiguous_shapes.empty());
  EXPECT_TRUE(report.summed_targets.empty());
  EXPECT_EQ(report.other_columns.size(), 9u);
  EXPECT_EQ(w[Index(kIctTargets, "cheekRaiser_L")], 0.0);
}

TEST(TakeTest, MatchesOtherSideConventions) {
  const Take take = ParseTake(
      "Timecode,BlendShapeCount,EyeBlinkLeft,EyeBlinkRight,BrowInnerUp,JawOpen,MouthSmileLeft,CheekPuff,Unknown\n"
      "00:00:00:00,7,0.1,0.2,0.3,0.4,0.5,0.6,0.7\n",
      "conventions.csv");
  const std::vector<std::string> targets = {"eyeBlinkL", "EyeBlink.R", "brow_inner_up_left", "Brow-Inner-Up Right",
                                            "JAWOPEN", "mouth_smile_Left", "cheekPuff"};
  const TakeFrames frames = MatchTake(take, targets);
  EXPECT_EQ(frames.weights[0], (std::vector<double>{0.1, 0.2, 0.3, 0.3, 0.4, 0.5, 0.6}));
  EXPECT_EQ(frames.report.unmatched_shapes, std::vector<std::string>{"Unknown"});
  EXPECT_TRUE(frames.report.undriven_targets.empty());
  EXPECT_FALSE(frames.report.timing.known);  // one row
}

TEST(TakeTest, AMapNamesTargetsWithFactors) {
  const Take take = ParseTake(
      "Timecode,BlendShapeCount,JawOpen,BrowInnerUp,TongueOut,Custom,HeadYaw\n00:00:00:00,5,0.6,0.25,0.75,0.4,0.3\n",
      "mapped.csv");
  const std::vector<std::string> targets = {"jaw", "browsUp", "lips", "jawOpen"};
  const ShapeMap map = ParseShapeMap(
      R"({"jawopen": {"jaw": 2.0, "lips": -1.5}, "BrowInnerUp": ["browsUp"], "TongueOut": null, "Custom": "lips",
          "EyeBlinkLeft": "jaw"})",
      "map.json");
  const TakeFrames frames = MatchTake(take, targets, &map);
  // lips: -1.5 * JawOpen + Custom (summed, in column order); jawOpen: mapped away from its own name, so undriven.
  EXPECT_EQ(frames.weights[0], (std::vector<double>{2.0 * 0.6, 0.25, 0.0 + -1.5 * 0.6 + 1.0 * 0.4, 0.0}));
  EXPECT_EQ(frames.report.undriven_targets, std::vector<std::string>{"jawOpen"});
  EXPECT_EQ(frames.report.summed_targets, std::vector<std::string>{"lips"});
  EXPECT_EQ(frames.report.unused_map_entries, std::vector<std::string>{"EyeBlinkLeft"});
  EXPECT_EQ(frames.report.unmatched_shapes, std::vector<std::string>{"TongueOut (null in the map)"});
  ASSERT_EQ(frames.report.out_of_range.size(), 2u);  // jaw above 1, lips below 0
  EXPECT_EQ(frames.report.out_of_range[0].target, "jaw");
  EXPECT_EQ(frames.report.out_of_range[1].target, "lips");

  const ShapeMap wrong = ParseShapeMap(R"({"JawOpen": "mouth"})", "wrong.json");
  try {
    MatchTake(take, targets, &wrong);
    ADD_FAILURE() << "an unknown target in the map was taken";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("wrong.json: \"JawOpen\": 'mouth' is not a target"), std::string::npos)
        << e.what();
  }
  EXPECT_THROW(ParseShapeMap(R"({"JawOpen": 3})", "m.json"), Error);
  EXPECT_THROW(ParseShapeMap(R"({"JawOpen": {"jaw": "x"}})", "m.json"), Error);
  EXPECT_THROW(ParseShapeMap("[1, 2]", "m.json"), Error);
}

TEST(TakeTest, LostRowsAreHeldOrSkippedAndCounted) {
  // Lost: the first two rows (before any tracked one), a long stretch of 500 and the last row.
  std::vector<bool> lost(700, false);
  lost[0] = lost[1] = true;
  for (int r = 100; r < 600; ++r) lost[r] = true;
  lost[699] = true;
  const Take take = ParseTake(MakeTake(700, 60, 2, 3600, 10, lost), "lost.csv");
  EXPECT_EQ(take.lost_rows(), 503);
  const std::vector<std::string> targets = {"jawOpen", "browInnerUp_L", "browInnerUp_R"};
  const TakeFrames held = MatchTake(take, targets, nullptr, LostRows::kHold);
  ASSERT_EQ(held.weights.size(), 700u);
  EXPECT_EQ(held.weights[0], held.weights[2]);    // the leading rows at the first tracked row's weights
  EXPECT_EQ(held.weights[350], held.weights[99]);  // held at the last tracked row
  EXPECT_EQ(held.weights[699], held.weights[698]);
  EXPECT_EQ(held.lines[350], 352);
  EXPECT_EQ(held.report.lost_rows, 503);
  EXPECT_EQ(held.report.leading_lost_rows, 2);
  EXPECT_EQ(held.report.longest_lost, 500);
  EXPECT_EQ(held.report.longest_lost_line, 102);
  const TakeFrames skipped = MatchTake(take, targets, nullptr, LostRows::kSkip);
  ASSERT_EQ(skipped.weights.size(), 197u);
  EXPECT_EQ(skipped.lines.front(), 4);
  EXPECT_EQ(skipped.lines[97], 101);
  EXPECT_EQ(skipped.lines[98], 602);
  // Timing is the take's either way: 30 fps from 01:00:00:10.
  EXPECT_EQ(take.timing.frame_rate, 30.0);
  EXPECT_EQ(take.timing.start_frame, (3600 * 60 + 10) / 2.0);

  std::vector<bool> all(5, true);
  try {
    MatchTake(ParseTake(MakeTake(5, 60, 2, 0, 0, all), "dead.csv"), targets);
    ADD_FAILURE() << "a take without tracked rows was taken";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("dead.csv: tracking was lost in every row"), std::string::npos);
  }
}

struct Rate {
  int timecode_rate, step, rows;
  long start_seconds;
  int start_frame;
};

class TakeTimingTest : public ::testing::TestWithParam<Rate> {};

TEST_P(TakeTimingTest, FrameRateAndStartFromTheTimecode) {
  const Rate r = GetParam();
  const Take take = ParseTake(MakeTake(r.rows, r.timecode_rate, r.step, r.start_seconds, r.start_frame), "t.csv");
  ASSERT_TRUE(take.timing.known);
  EXPECT_EQ(take.timing.timecode_rate, r.timecode_rate);
  EXPECT_EQ(take.timing.step, r.step);
  EXPECT_EQ(take.timing.frame_rate, static_cast<double>(r.timecode_rate) / r.step);
  EXPECT_EQ(take.timing.start_frame,
            (static_cast<double>(r.start_seconds) * r.timecode_rate + r.start_frame) / r.step);
}

INSTANTIATE_TEST_SUITE_P(Rates, TakeTimingTest,
                         ::testing::Values(Rate{24, 1, 100, 10, 0}, Rate{25, 1, 60, 0, 3}, Rate{30, 1, 31, 59, 29},
                                           Rate{60, 1, 200, 86399, 30},  // past midnight
                                           Rate{60, 2, 3000, 61000, 37},  // odd phase: start at a half frame
                                           Rate{50, 2, 80, 7, 48}, Rate{120, 4, 90, 100, 0}));

TEST(TakeTest, ATakeShorterThanASecondAssumesAUsualRate) {
  const Take take = ParseTake(MakeTake(10, 60, 2, 100, 0), "short.csv");  // frames 0..18, no wrap
  ASSERT_TRUE(take.timing.known);
  EXPECT_TRUE(take.timing.rate_assumed);
  EXPECT_EQ(take.timing.timecode_rate, 24);  // the smallest usual rate above 18
  EXPECT_EQ(take.timing.step, 2);
  const TakeFrames frames = MatchTake(take, {"jawOpen"});
  EXPECT_NE(frames.report.Lines().front().find("assumed"), std::string::npos);
}

TEST(TakeTest, ReportsWeightsOutsideZeroToOne) {
  const Take take = ParseTake(
      "Timecode,BlendShapeCount,EyeLookOutLeft,JawOpen\n00:00:00:00,2,0.5,0\n00:00:00:01,2,1.0234,-0.01\n"
      "00:00:00:02,2,1.5,0.2\n",
      "range.csv");
  const TakeFrames frames = MatchTake(take, {"eyeLookOut_L", "jawOpen"});
  ASSERT_EQ(frames.report.out_of_range.size(), 2u);
  const auto& eye = frames.report.out_of_range[0];
  EXPECT_EQ(eye.target, "eyeLookOut_L");
  EXPECT_EQ(eye.frames, 2);
  EXPECT_EQ(eye.low, 1.0234);
  EXPECT_EQ(eye.high, 1.5);
  EXPECT_EQ(eye.line, 3);
  EXPECT_EQ(frames.report.out_of_range[1].low, -0.01);
  EXPECT_EQ(frames.weights[2][0], 1.5);  // reported, never clamped
}

TEST(TakeTest, BadTakesNameTheLineAndColumn) {
  const std::string header = "Timecode,BlendShapeCount,JawOpen,MouthClose,HeadYaw\n";
  EXPECT_EQ(TakeError(header + "00:00:00:00,3,0.1,0.2,0\n00:00:00:01,3,0.1\n"),
            "bad.csv: line 3, column 4: the row ends after 3 of the header's 5 columns (a row where tracking was "
            "lost has BlendShapeCount 0)");
  EXPECT_EQ(TakeError(header + "00:00:00:00,3,0.1,abc,0\n"), "bad.csv: line 2, column 4: (MouthClose) 'abc' is not a number");
  EXPECT_EQ(TakeError(header + "00:00:00:00,3,0.1,nan,0\n"), "bad.csv: line 2, column 4: (MouthClose) 'nan' is not a number");
  EXPECT_EQ(TakeError(header + "00:00:00:00,3,0.1,0.2,x\n"), "bad.csv: line 2, column 5: (HeadYaw) 'x' is not a number");
  EXPECT_EQ(TakeError(header + "\n00:00:00:00,3,0.1,0.2,0,9\n"),
            "bad.csv: line 3, column 6: 6 fields, but the header has 5 columns");
  EXPECT_EQ(TakeError(header + "0:00:61:00,3,0.1,0.2,0\n"),
            "bad.csv: line 2, column 1: (Timecode) '0:00:61:00' is not a timecode HH:MM:SS:FF[.sss]");
  EXPECT_EQ(TakeError(header + "00:00:00:00,x\n"), "bad.csv: line 2, column 2: (BlendShapeCount) 'x' is not a number");
  EXPECT_EQ(TakeError("Frame,Alpha,Beta\n1,2,3\n"),
            "bad.csv: line 1, column 1: not a take's header: no Timecode, BlendShapeCount or ARKit shape column "
            "(EyeBlinkLeft ... JawOpen ... TongueOut)");
  EXPECT_EQ(TakeError("Timecode,BlendShapeCount,,JawOpen\n"), "bad.csv: line 1, column 3: a column without a name");
  EXPECT_EQ(TakeError(header), "bad.csv: the take has a header but no rows");
  EXPECT_EQ(TakeError("Timecode,BlendShapeCount,HeadYaw\n00:00:00:00,1,0\n"),
            "bad.csv: line 1, column 1: the header names no shape column (only timecode and rotations)");
  // A lost-tracking row (BlendShapeCount 0, only a timecode) is no error; CRLF line ends and a BOM are fine.
  const Take take = ParseTake("\xEF\xBB\xBF" + header + "00:00:00:00,0\r\n00:00:00:01,3,1,2,3\r\n", "ok.csv");
  EXPECT_EQ(take.lost_rows(), 1);
  EXPECT_EQ(take.rows[1].values, (std::vector<double>{1, 2}));
  // A header whose shapes none of the rig's targets match.
  try {
    MatchTake(take, {"bend", "twist"});
    ADD_FAILURE() << "a take driving nothing was taken";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("ok.csv: line 1: no column of the header is a shape of this rig"),
              std::string::npos)
        << e.what();
  }
}

TEST(TakeTest, RecognisesATakeByItsHeader) {
  EXPECT_TRUE(LooksLikeTake(DataPath("take/alex_rom_4_excerpt.csv")));
  EXPECT_FALSE(LooksLikeTake(DataPath("cylinder/rig.json")));
  EXPECT_FALSE(LooksLikeTake(DataPath("no/such/file.csv")));
}

}  // namespace
}  // namespace springblend::cli
