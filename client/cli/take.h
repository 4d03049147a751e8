// Captured facial performances ("takes", docs/takes.md): a Live Link Face CSV (Epic's iOS app, ARKit's 52 shapes per
// frame; other capture tools write the same names) read into per-frame weights of a rig's targets. Reading and
// matching are separate: a take is read once (ReadTake: columns, rows, timing) and matched to any rig's target names
// (MatchTake: names, the user's map, lost-tracking rows, and a report of everything that was not a plain match).
// The Python client's springblend.performance implements the same rules; tests/data/take checks the two agree.
// Every error names the file, and for a bad row its line and column (1-based).
#pragma once

#include <string>
#include <utility>
#include <vector>

namespace springblend::cli {

struct TakeRow {
  int line = 0;                // in the file, 1-based (the header is line 1)
  std::string timecode;        // as written; empty when the take has no Timecode column
  bool tracked = true;         // false: BlendShapeCount 0, tracking was lost (no weights)
  std::vector<double> values;  // one per shape column when tracked
};

// When the rows were captured, from the Timecode column (HH:MM:SS:FF, optionally .sss subframes, ';' for
// drop-frame). The timecode counts timecode_rate frames per second and steps by `step` per row (Live Link Face:
// 60 per second, step 2 for a 30 fps take).
struct TakeTiming {
  bool known = false;        // false without a Timecode column or with fewer than two rows a second apart or less
  int timecode_rate = 0;     // frames per second the timecode counts (FF < timecode_rate)
  int step = 0;              // timecode frames per row
  double frame_rate = 0.0;   // rows per second: timecode_rate / step
  double start_frame = 0.0;  // the first row's timecode counted in take frames: (seconds of the day * rate + FF) / step
  bool rate_assumed = false; // the take spans no second boundary: timecode_rate is the smallest usual rate above FF
};

struct Take {
  std::string source;                      // the path, for messages
  std::vector<std::string> shapes;         // the weight columns' names, in file order
  std::vector<int> shape_columns;          // their columns (0-based)
  std::vector<std::string> other_columns;  // columns that are not weights (head and eye rotations), left out
  std::vector<TakeRow> rows;
  TakeTiming timing;
  int lost_rows() const;
};

// Whether the file's first line is a take's header (a Timecode or BlendShapeCount column, or an ARKit shape name):
// how --frames tells a take from a JSON scene file.
bool LooksLikeTake(const std::string& path);

// Reads a take. Throws Error (kNotFound: no such file; kInvalidInput: "take.csv: line 7, column 19 (JawOpen):
// 'x' is not a number") for a row that is neither full nor a lost-tracking row, a field that is not a number or a
// timecode, a header with an empty name or no weight column, or a take without rows.
Take ReadTake(const std::string& path);
Take ParseTake(const std::string& text, const std::string& source);

// A user's map (--map FILE, JSON): {"ShapeName": "target" | ["target", ...] | {"target": factor, ...} | null}.
// A shape in the map drives exactly its entries (null or {}: nothing); the others are matched by name.
struct ShapeMap {
  std::string source;
  std::vector<std::pair<std::string, std::vector<std::pair<std::string, double>>>> entries;
};
ShapeMap LoadShapeMap(const std::string& path);
ShapeMap ParseShapeMap(const std::string& text, const std::string& source);

enum class LostRows { kHold, kSkip };
LostRows LostRowsFromString(const std::string& name);  // "hold" or "skip"; throws Error naming --lost

// What a take's match to a rig left out or changed, said once (docs/takes.md#the-report).
struct TakeReport {
  std::string source;
  int rows = 0, frames = 0;
  TakeTiming timing;
  std::vector<std::string> other_columns;      // not weights, left out
  std::vector<std::string> unmatched_shapes;   // drive no target
  std::vector<std::string> ambiguous_shapes;   // "Name (a, b)": several targets fit by name; drive none
  std::vector<std::string> unused_map_entries; // map entries for shapes the take lacks
  std::vector<std::string> undriven_targets;   // no column drives them: 0 in every frame
  std::vector<std::string> summed_targets;     // driven by several columns: their sum
  struct OutOfRange {
    std::string target;
    int frames = 0;            // frames with the target's weight outside [0, 1]
    double low = 0, high = 0;  // its extremes over the take
    int line = 0;              // where the first such frame is
  };
  std::vector<OutOfRange> out_of_range;
  LostRows lost = LostRows::kHold;
  int lost_rows = 0, leading_lost_rows = 0, longest_lost = 0, longest_lost_line = 0;
  // One line per finding, without a prefix; empty when there is nothing to say beyond the counts.
  std::vector<std::string> Lines() const;
};

struct TakeFrames {
  std::vector<std::vector<double>> weights;  // per frame, one per target in `targets` order
  std::vector<int> lines;                    // the file line each frame came from
  TakeReport report;
};

// The take's rows as weights of the targets. Names match case-insensitively, ignoring '_', '.', '-' and spaces,
// with a side suffix (Left/Right, _L/_R, .L/.R, L/R after a lower-case letter) matching any other side
// convention; an exact name (case-insensitive) wins; a shape without a side drives both halves of a target the
// rig splits into left and right. The map overrides names for the shapes it lists; factors scale, and several
// columns driving one target add up. Lost rows are held at the last tracked row (leading ones at the first
// tracked row) or skipped. Throws Error naming the map for an entry whose target the rig lacks, and the take when
// no column drives any target or every row is lost.
TakeFrames MatchTake(const Take& take, const std::vector<std::string>& targets, const ShapeMap* map = nullptr,
                     LostRows lost = LostRows::kHold);

}  // namespace springblend::cli
