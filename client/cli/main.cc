// springblend: the command line. `springblend blend` solves locally with the solver library.
#include <tbb/global_control.h>

#include <CLI/CLI.hpp>
#include <iostream>
#include <memory>

#include "commands.h"
#include "springblend/error.h"
#include "springblend/runtime.h"
#include "springblend/version.h"

int main(int argc, char** argv) {
  using namespace springblend;
  ConfigureNumericalThreads(argv);
  CLI::App app{"springblend: physically based blendshapes (rest-length interpolation of a mass-spring system)"};
  app.require_subcommand(1);
  app.set_version_flag("--version", std::string("springblend ") + SPRINGBLEND_VERSION);
  int threads = 0;
  app.add_option("--threads", threads, "worker threads for assembly (0: all cores)")->check(CLI::Range(0, 1024));
  cli::Runner blend = cli::AddBlendCommand(app);
  cli::Runner bake = cli::AddBakeCommand(app);
  const auto remote = cli::AddServiceCommands(app);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? cli::kExitOk : cli::kExitBadInput;
  }
  std::unique_ptr<tbb::global_control> limit;
  if (threads > 0) {
    limit = std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism,
                                                  static_cast<size_t>(threads));
  }
  try {
    if (app.got_subcommand("blend")) return blend();
    if (app.got_subcommand("bake-rig")) return bake();
    for (const auto& [name, run] : remote) {
      if (app.got_subcommand(name)) return run();
    }
    return cli::kExitBadInput;
  } catch (const Error& e) {
    std::cerr << "springblend: error: " << e.what() << "\n";
    return e.code() == ErrorCode::kInternal ? cli::kExitInternal : cli::kExitBadInput;
  } catch (const std::exception& e) {
    std::cerr << "springblend: internal error: " << e.what() << "\n";
    return cli::kExitInternal;
  }
}
