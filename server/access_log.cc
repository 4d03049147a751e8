#include "access_log.h"

#include <fmt/chrono.h>
#include <fmt/format.h>
#include <spdlog/pattern_formatter.h>
#include <nlohmann/json.hpp>
#include <spdlog/spdlog.h>

#include <atomic>
#include <cmath>
#include <chrono>
#include <random>

#include "status.h"

namespace springblend::server {
namespace {

std::atomic<bool> json_logs{false};

std::string NewRequestId() {
  thread_local std::mt19937_64 generator{std::random_device{}()};
  return fmt::format("{:016x}", generator());
}

bool Usable(const std::string& id) {
  if (id.empty() || id.size() > 128) return false;
  for (unsigned char c : id) {
    if (c < 0x21 || c > 0x7e) return false;
  }
  return true;
}

// JSON text (bytes that are not UTF-8 replaced, as a client's may be).
std::string Dump(const nlohmann::ordered_json& value) {
  return value.dump(-1, ' ', false, nlohmann::ordered_json::error_handler_t::replace);
}

std::string Timestamp(std::chrono::system_clock::time_point time) {
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(time.time_since_epoch()).count() % 1000;
  return fmt::format("{:%Y-%m-%dT%H:%M:%S}.{:03d}Z", fmt::gmtime(std::chrono::system_clock::to_time_t(time)), ms);
}

// spdlog's lines as {"time": ..., "level": ..., "message": ...}; a message that is already a JSON object's members
// (access lines: `"access":...`) is spliced in as they are.
class JsonFormatter final : public spdlog::formatter {
 public:
  void format(const spdlog::details::log_msg& msg, spdlog::memory_buf_t& dest) override {
    const std::string_view payload(msg.payload.data(), msg.payload.size());
    const auto level = spdlog::level::to_string_view(msg.level);
    std::string line = fmt::format("{{\"time\":\"{}\",\"level\":\"{}\",", Timestamp(msg.time),
                                   std::string_view(level.data(), level.size()));
    if (payload.rfind("\"access\":", 0) == 0) {
      line += payload;
    } else {
      line += "\"message\":" + Dump(std::string(payload));
    }
    line += "}\n";
    dest.append(line.data(), line.data() + line.size());
  }
  std::unique_ptr<spdlog::formatter> clone() const override { return std::make_unique<JsonFormatter>(); }
};

}  // namespace

CallInfo BeginCall(grpc::CallbackServerContext* call, const char* method) {
  CallInfo info;
  info.method = method;
  info.peer = call->peer();
  const auto& metadata = call->client_metadata();
  const auto given = metadata.find(kRequestIdHeader);
  if (given != metadata.end()) info.request_id.assign(given->second.data(), given->second.size());
  if (!Usable(info.request_id)) info.request_id = NewRequestId();
  call->AddInitialMetadata(kRequestIdHeader, info.request_id);
  return info;
}

void EndCall(Metrics& metrics, const CallInfo& call, const grpc::Status& status) {
  const std::string code = CodeName(status.error_code());
  metrics.CountRequest(call.method, code, call.started);
  const double ms = std::chrono::duration<double, std::milli>(MetricsClock::now() - call.started).count();
  const std::string character = call.character.substr(0, 12);
  if (json_logs) {
    // The members of one object, "access" first: the formatter splices them into the line's object.
    nlohmann::ordered_json fields = {{"access", true},           {"method", call.method},
                                     {"status", code},           {"ms", std::round(ms * 10.0) / 10.0},
                                     {"peer", call.peer},        {"request_id", call.request_id}};
    if (!character.empty()) fields["character"] = character;
    if (call.frames >= 0) fields["frames"] = call.frames;
    if (!status.ok()) fields["error"] = status.error_message().substr(0, 400);
    const std::string object = Dump(fields);
    spdlog::info("{}", std::string_view(object).substr(1, object.size() - 2));
  } else {
    spdlog::info("access {} {}{}{} {:.1f} ms peer={} request_id={}", call.method, code,
                 character.empty() ? "" : " character=" + character,
                 call.frames >= 0 ? fmt::format(" frames={}", call.frames) : "", ms, call.peer, call.request_id);
  }
}

void SetJsonLogs(bool json) {
  json_logs = json;
  if (json) spdlog::default_logger()->set_formatter(std::make_unique<JsonFormatter>());
}

}  // namespace springblend::server
