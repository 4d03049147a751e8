// Subcommands of the springblend CLI. Each registers its options on the app and returns the function
// that runs it (after parsing); the function returns the process exit code.
#pragma once

#include <CLI/CLI.hpp>
#include <functional>
#include <string>
#include <utility>
#include <vector>

namespace springblend::cli {

// Exit codes shared by every subcommand.
inline constexpr int kExitOk = 0;
inline constexpr int kExitNotConverged = 1;  // ran, but some frame did not converge
inline constexpr int kExitBadInput = 2;      // bad arguments, files or weights (message on stderr)
inline constexpr int kExitInternal = 3;
inline constexpr int kExitUnavailable = 4;  // the server is unreachable, busy or failing

using Runner = std::function<int()>;

Runner AddBlendCommand(CLI::App& app);
// bake-rig: a rig's physics baked into a plain blendshape rig (bake_command.cc).
Runner AddBakeCommand(CLI::App& app);
// upload, solve, list, delete, health: name and runner of each.
std::vector<std::pair<std::string, Runner>> AddServiceCommands(CLI::App& app);

}  // namespace springblend::cli
