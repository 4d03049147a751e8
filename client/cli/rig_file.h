// Rig files (README: rig files): a production rig in JSON, shared by `springblend blend --rig` and
// `springblend upload --rig`. Loading reads every mesh and mask and checks what the JSON says (keys, types,
// files, mask lengths and numbers); the rig's own rules (in-between weights, combination drivers, topology) are
// the solver's, or the server's, to check. Every message starts with the rig file's path.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "springblend/client.h"
#include "springblend/rig.h"

namespace springblend::cli {

struct RigFile {
  std::string path;
  TriangleMesh rest;
  std::vector<int> fixed_vertices;
  std::vector<RigTarget> targets;  // in file order, combinations included

  // The weight order of frames: the targets that are not combinations.
  std::vector<std::string> WeightNames() const;
};

// Throws Error(kInvalidInput or kNotFound) "RIG.json: target 'jawOpen': inbetweens[0].mesh: ...".
RigFile LoadRigFile(const std::string& path);

// Builds the rig locally (options.fixed_vertices gains the file's); the solver's refusals ("target 'jawOpen':
// inbetweens[1].weight ...") get the rig file's path in front.
std::shared_ptr<const Rig> BuildRig(RigFile file, RigOptions options);

// The rig a local command's flags name: --rig RIG.json, or --rest REST with --target T...; refuses both or neither
// (`otherwise` ends that message with what else the command takes, e.g. ", or --server and --character").
std::shared_ptr<const Rig> BuildRigFromFlags(const std::string& rig, const std::string& rest,
                                             const std::vector<std::string>& targets, const RigOptions& options,
                                             const std::string& otherwise = "");

// A mask text file: one number per line (blank lines and lines starting with # are skipped). Throws naming
// `source` and the line.
std::vector<double> ParseMaskText(const std::string& text, const std::string& source);

}  // namespace springblend::cli
