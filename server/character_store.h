// The character cache: built rigs in memory (least recently used out first, within a byte budget) over a
// directory of content-addressed upload files, so a restart, or another replica sharing the directory,
// serves a known character without a re-upload. Ids are SHA-256 hex digests, never paths.
//
// A cache file, ID.sbchar (version 2), keeps what the rig is built from and what is costly to build again:
//   "SBCHAR02" | SHA-256(payload) | u64 payload length | payload | SHA-256(precomputed) | precomputed
// payload = Serialize(CharacterData) (the id is its hash without the name), precomputed = Rig::SavePrecomputed
// (the target paths), which a rebuild from the file loads rather than solves. Version 1 ("SBCHAR01" |
// SHA-256(payload) | payload) still loads; its paths are solved and the file is rewritten as version 2.
#pragma once

#include <atomic>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <future>
#include <list>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "springblend/rig.h"

namespace springblend::server {

// The production-rig parts of one target (proto TargetRig): in-betweens, mask, combination drivers.
struct TargetRigData {
  std::vector<double> inbetween_weights;
  std::vector<Points> inbetweens;  // one per weight, the rest mesh's vertex count
  std::vector<double> mask;        // empty, or one per vertex
  std::vector<std::string> combination;
};

// Everything that defines a character: the meshes and the build options.
struct CharacterData {
  std::string name;  // a label, not part of the id
  std::vector<std::string> target_names;  // every target, combinations included
  Faces faces;
  std::vector<Points> shapes;  // rest, then one per target
  RigOptions options;
  // Empty (every target plain: the id is what it was before production rigs), or one per target. In-betweens,
  // masks and combinations are part of the canonical bytes, so they change the id.
  std::vector<TargetRigData> target_rigs;
};

// The canonical bytes of a character (what is hashed and stored) and back.
std::string Serialize(const CharacterData& data);
CharacterData Deserialize(const std::string& bytes);  // throws Error(kInvalidInput) when malformed
std::string ContentId(const CharacterData& data);       // hex SHA-256 of Serialize without the name

struct StoreOptions {
  std::string directory;  // empty: memory only
  std::int64_t memory_budget_bytes = 4LL << 30;
};

struct StoreStats {
  std::int64_t hits = 0, misses = 0, evictions = 0, bytes = 0, characters = 0, rebuilds_from_disk = 0,
               corrupt_files = 0;
  std::int64_t builds = 0;  // rigs built (uploads and rebuilds, failed ones too): concurrent requests share one
  std::int64_t paths_loaded = 0;     // rebuilds from the directory that loaded their target paths from the file
  std::int64_t upgraded_files = 0;   // cache files rewritten because their paths were missing (v1) or did not fit
  std::int64_t cancelled_builds = 0;  // builds their stop check ended
  std::int64_t write_failures = 0;    // cache files that could not be written (a read-only or full directory)
};

// Asked while a build runs (RigBuildControl::stop, on the building threads): true ends the build with
// Error(kCancelled). Empty: never.
using StopCheck = std::function<bool()>;

class CharacterStore {
 public:
  struct Entry {
    std::string id;
    std::string name;
    std::shared_ptr<const Rig> rig;
    std::int64_t bytes = 0;
  };

  explicit CharacterStore(StoreOptions options);

  // Builds (or finds) the character. Returns the entry and whether it was already known. Concurrent Puts and
  // Gets of one id share one build, which runs with the stop check of the caller that started it; a caller
  // waiting for another's build stops waiting when its own check says so. When `stop` ends a build, it throws
  // Error(kCancelled) and nothing is kept (no entry, no file); the callers waiting for that build who did not
  // stop build it again themselves.
  std::pair<std::shared_ptr<const Entry>, bool> Put(const CharacterData& data, const StopCheck& stop = {});
  // From memory, else from the directory (rebuilding the rig, with the file's target paths); nullptr if unknown
  // anywhere. Concurrent calls for one cold id share one rebuild, as Put's do.
  std::shared_ptr<const Entry> Get(const std::string& id, const StopCheck& stop = {});
  // Built characters in memory, most recently used first, then those only in the cache directory (listed by
  // id and name without building them: `entry` is null). A file is checked (checksum, id) the first time it
  // is listed; a corrupt one is removed, logged, and not listed.
  struct Listed {
    std::string id, name;
    std::shared_ptr<const Entry> entry;
  };
  std::vector<Listed> List();
  // Removes the character from memory and the directory. A build of it in flight (an upload, or a rebuild
  // from the cache file) finishes for its callers but is not kept: the delete wins.
  bool Delete(const std::string& id);
  StoreStats stats() const;

  // Removes the temporary files writers killed mid-write (kill -9, OOM, power loss) left in the cache
  // directory: only regular files named like WriteFile's temporaries (ID.sbchar.tmp.PID.SUFFIX) that no live
  // writer holds. A writer, here or in another replica sharing the directory, holds a lock on its temporary until
  // the rename, so its file is kept (`in_use`). Nothing else in the directory is touched. Run at start-up.
  struct Cleanup {
    int removed = 0;  // stale temporaries deleted
    int in_use = 0;   // temporaries a live writer holds, kept
  };
  Cleanup RemoveStaleTemporaries();

  static bool ValidId(const std::string& id);

 private:
  // A cache file's two parts; no precomputed part in a version 1 file.
  struct CacheFile {
    std::string payload;
    CharacterData data;  // the payload read
    std::optional<std::string> precomputed;
  };
  std::shared_ptr<const Entry> Build(const std::string& id, const CharacterData& data, const RigBuildControl& control);
  // The rig of a cache file, its paths loaded when the file has them; rewrites a file whose paths were
  // missing or did not fit.
  std::shared_ptr<const Entry> Rebuild(const std::string& id, const CacheFile& file, const StopCheck& stop);
  // The one build of `id` in flight: from `data` when given (an upload), else from the cache file.
  std::pair<std::shared_ptr<const Entry>, bool> Acquire(const std::string& id, const CharacterData* data,
                                                        const StopCheck& stop);
  void Insert(std::shared_ptr<const Entry> entry);  // caller holds mutex_
  std::string PathOf(const std::string& id) const;
  void WriteFile(const std::string& id, const std::string& payload, const std::string& precomputed) const;
  // The checked parts of the cache file; nullopt when there is none, or it is corrupt (then it is removed).
  std::optional<CacheFile> ReadFile(const std::string& id);

  StoreOptions options_;
  mutable std::mutex mutex_;
  std::list<std::string> lru_;  // most recent first
  struct Slot {
    std::shared_ptr<const Entry> entry;
    std::list<std::string>::iterator position;
  };
  std::unordered_map<std::string, Slot> entries_;
  struct Flight {
    std::shared_future<std::shared_ptr<const Entry>> result;
    bool deleted = false;  // a Delete came while it built: do not keep the result
  };
  std::unordered_map<std::string, std::shared_ptr<Flight>> building_;
  struct FileStamp {
    std::uintmax_t size = 0;
    std::filesystem::file_time_type modified;
  };
  std::unordered_map<std::string, FileStamp> verified_;  // cache files List has checked
  StoreStats stats_;
  mutable std::atomic<std::int64_t> write_failures_{0};  // StoreStats::write_failures (WriteFile is const)
};

}  // namespace springblend::server
