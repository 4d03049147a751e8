#include "frame_output.h"

#include <fmt/format.h>

#include <filesystem>

#include "springblend/error.h"
#include "springblend/mesh.h"

namespace springblend::cli {
namespace {

template <typename Fn>
auto AsInputError(Fn&& fn) {
  try {
    return fn();
  } catch (const PointCacheError& e) {
    throw Error(ErrorCode::kInvalidInput, e.what());
  }
}

}  // namespace

void AddCacheTimingOptions(CLI::App* command, CacheTiming* timing) {
  const auto given = [timing](const auto&) { timing->given = true; };
  command->add_option("--start-frame", timing->start_frame, "a .pc2 output's first frame (default 1)")
      ->each(given)
      ->check(CLI::Range(-1e7, 1e7));
  command->add_option("--sample-rate", timing->sample_rate,
                      "a .pc2 output's frames per sample (default 1; 0.5 = two samples per frame)")
      ->each(given)
      ->check(CLI::Range(1e-6, 1e6));
}

FrameOutput::FrameOutput(std::string out, bool many, Faces faces, int vertices, const CacheTiming& timing)
    : out_(std::move(out)), many_(many), faces_(std::move(faces)) {
  if (IsPointCachePath(out_)) {
    cache_ = AsInputError([&] {
      return std::make_unique<PointCacheWriter>(out_, vertices, static_cast<float>(timing.start_frame),
                                                static_cast<float>(timing.sample_rate));
    });
  } else if (timing.given) {
    throw Error(ErrorCode::kInvalidInput,
                fmt::format("--start-frame and --sample-rate place a point cache's samples; --out {} is not a .pc2 "
                            "file",
                            out_));
  } else if (many_) {
    std::error_code ec;
    std::filesystem::create_directories(out_, ec);
    if (ec || !std::filesystem::is_directory(out_)) {
      throw Error(ErrorCode::kInvalidInput, "cannot create the output directory " + out_);
    }
  }
}

void FrameOutput::Write(int index, const Points& positions) {
  if (cache_) {
    if (index != cache_->samples()) {
      throw Error(ErrorCode::kInternal, fmt::format("{}: frame {} came before frame {}", out_, index, cache_->samples()));
    }
    AsInputError([&] { cache_->Add(positions); });
    return;
  }
  const std::string path =
      many_ ? (std::filesystem::path(out_) / fmt::format("frame_{:04d}.obj", index)).string() : out_;
  WriteObj(path, positions, faces_);
}

void FrameOutput::Finish() {
  if (cache_) AsInputError([&] { cache_->Close(); });
}

}  // namespace springblend::cli
