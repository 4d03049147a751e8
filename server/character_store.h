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

#include <sys/stat.h>

#include <atomic>
#include <chrono>
#include <exception>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <list>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "solver_pool.h"
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

// Asked while a build runs (RigBuildControl::stop, on the building threads): true ends the build with
// Error(kCancelled). Empty: never.
using StopCheck = std::function<bool()>;

struct StoreOptions {
  std::string directory;  // empty: memory only
  std::int64_t memory_budget_bytes = 4LL << 30;
  // Builds (uploads, and rebuilds from the directory) run on threads of their own, never on a caller's: this
  // many at once, and this many more waiting for a thread; beyond, a new build is refused (LimitError).
  int build_threads = 1;
  int build_queue = 8;
  StopCheck stop;  // every build stops when it says true (the server's shutdown): asked between path samples
};

// How a build goes, for whoever waits for it.
struct BuildProgress {
  RigBuildProgress rig;      // stage "queued" until a build thread takes it
  bool from_file = false;    // a rebuild from the cache directory (its paths loaded, not solved)
  double estimate_ms = 0.0;  // the whole build's expected time, from the paths done so far; 0 while unknown
};

struct StoreStats {
  std::int64_t hits = 0, misses = 0, evictions = 0, bytes = 0, characters = 0, rebuilds_from_disk = 0,
               corrupt_files = 0;
  std::int64_t builds = 0;  // rigs built (uploads and rebuilds, failed ones too): concurrent requests share one
  std::int64_t paths_loaded = 0;     // rebuilds from the directory that loaded their target paths from the file
  std::int64_t upgraded_files = 0;   // cache files rewritten because their paths were missing (v1) or did not fit
  std::int64_t cancelled_builds = 0;  // builds their stop check ended
  std::int64_t write_failures = 0;    // cache files that could not be written (a read-only or full directory)
  int build_threads = 0, builds_running = 0, builds_queued = 0;  // the build threads, busy, and builds waiting
};

class CharacterStore {
 public:
  // A part of a cache file: bytes [offset, offset + size).
  struct FilePart {
    std::int64_t offset = 0;
    std::int64_t size = 0;
  };
  struct Entry {
    std::string id;
    std::string name;
    std::shared_ptr<const Rig> rig;
    std::int64_t bytes = 0;
    // SHA-256 of the rig's precomputed paths as they were written to, or loaded from, its cache file; empty when
    // they were not. A cache file written anew from the rig must give the same (else the rig is damaged).
    std::string paths_digest;
    // Why its upload's cache file could not be written (a read-only or full directory, no descriptor left): it is
    // served from memory only, unknown to a restart or another replica. Empty when written, or memory only.
    std::string not_persisted;
  };

  explicit CharacterStore(StoreOptions options);
  ~CharacterStore();  // waits for the builds running (StoreOptions::stop should say stop first); queued ones end

  // A build in flight, an upload's or a rebuild from the cache directory, shared by everyone who waits for it.
  // It goes on while at least one of its waiters still wants it (Found::waiter), and stops within a path sample
  // or Newton iteration once none does, or StoreOptions::stop says so: then it ends with Error(kCancelled)
  // and nothing is kept (no entry, no file).
  class PendingBuild;
  // Someone waiting for a build: dropping it says it does not want the build any more.
  using Waiter = std::shared_ptr<void>;
  // Whether a waiter still wants its build (its call is not cancelled and within its deadline). Asked on the
  // building threads, with the store's lock held: keep it short.
  using Wants = std::function<bool()>;
  struct Found {
    std::shared_ptr<const Entry> entry;        // built, in memory
    std::shared_ptr<PendingBuild> building;    // being built: wait with PendingBuild::OnDone, holding `waiter`
    Waiter waiter;
    bool stored = false;  // Find without rebuild: only in the cache directory
    bool known = true;    // Start: it was in memory, being built or in the cache directory already
    bool joined = false;  // `building` was already in flight (another caller's), not started for this one
  };
  // Never waits for a build. In memory: the entry. Being built: that build. Only in the cache directory: a
  // rebuild started (`rebuild`), or `stored`. Unknown anywhere: nothing. Throws LimitError when a rebuild is
  // needed and the build queue is full.
  Found Find(const std::string& id, bool rebuild, Wants wants);
  // Never waits for a build: the character as Find finds it (rebuilding from the file when there is one), else
  // a build of `data` started. Throws LimitError when the build queue is full.
  Found Start(CharacterData data, Wants wants);
  // Waits on this thread (for tests and tools; the server never does): the entry of `found`, or the error of
  // its build; `stop` (asked every 20 ms) ends the wait with Error(kCancelled).
  static std::shared_ptr<const Entry> Wait(Found found, const StopCheck& stop = {});

  // Start and Wait: the entry, and whether it was already known.
  std::pair<std::shared_ptr<const Entry>, bool> Put(const CharacterData& data, const StopCheck& stop = {});
  // Find (rebuilding from the directory) and Wait; nullptr if unknown anywhere.
  std::shared_ptr<const Entry> Get(const std::string& id, const StopCheck& stop = {});
  // Built characters in memory, most recently used first, then those being built, then those only in the cache
  // directory (listed by id and name without building them: `entry` is null). A file is checked (checksum, id)
  // the first time it is listed; a corrupt one is removed, logged, and not listed.
  struct Listed {
    std::string id, name;
    std::shared_ptr<const Entry> entry;
    std::shared_ptr<PendingBuild> building;  // being built (then `entry` is null; `name` empty for a rebuild)
  };
  std::vector<Listed> List();
  // Removes the character from memory and the directory. A build of it in flight (an upload, or a rebuild
  // from the cache file) finishes for its callers but is not kept: the delete wins.
  bool Delete(const std::string& id);
  // The entry's rig is damaged (its paths could not be read back from its cache file: DataLossError): it leaves
  // memory, so the next call that needs the character rebuilds it (from its file when that is whole) and the next
  // upload builds it anew; the file is checked again before it is listed. False when it was not in memory.
  bool Drop(const std::shared_ptr<const Entry>& entry, const std::string& why);
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
    std::optional<FilePart> precomputed;  // where the file's precomputed paths are (checked); none in version 1
    std::string paths_digest;             // their SHA-256, as checked
    std::shared_ptr<const OpenFile> opened;  // the file checked, for the rig to read its paths through
  };
  std::shared_ptr<Entry> Build(const std::string& id, const CharacterData& data, const RigBuildControl& control);
  // The rig of a cache file, its paths loaded when the file has them; rewrites a file whose paths were
  // missing or did not fit.
  std::shared_ptr<const Entry> Rebuild(const std::string& id, const CacheFile& file, const RigBuildControl& control);
  // Find and Start: the entry, the build in flight, or a build started (from the file when there is one, else
  // from `data` when given).
  Found Lookup(const std::string& id, CharacterData* data, bool rebuild, Wants wants);
  // On a build thread: the build of `flight`, then its waiters told.
  void RunBuild(const std::shared_ptr<PendingBuild>& flight, const std::shared_ptr<const CharacterData>& data);
  // The build's stop check: the store's stop, or no waiter wants it any more (then it is taken out of
  // building_ at once, so a new caller starts a build of its own rather than join one that is stopping).
  bool Abandoned(const std::shared_ptr<PendingBuild>& flight);
  void Insert(std::shared_ptr<const Entry> entry);  // caller holds mutex_
  // Evicts the least recently used entries no one else holds until the budget is met (or only the most recently
  // used one, or entries in use, are left); the caller holds mutex_.
  void Trim();
  std::string PathOf(const std::string& id) const;
  // Where the precomputed part landed (for the rig to read its samples from), nullopt when not written.
  // The precomputed part is told by `precomputed` in pieces (a rig's WritePrecomputed), never held together.
  // What a write gave: the SHA-256 of the precomputed part written, or why nothing was.
  struct Written {
    std::string paths_digest;
    std::string failure;
  };
  // `written` (when given) says how it went. Throws DataLossError (nothing written) when the rig's own paths
  // cannot be read back from the file they were left in, or (`expected` given) are not those it was built with.
  std::optional<PrecomputedLocation> WriteFile(const std::string& id, const std::string& payload,
                                               const PrecomputedWriter& precomputed, Written* written = nullptr,
                                               const std::string& expected = {});
  std::optional<PrecomputedLocation> WriteFile(const std::string& id, const std::string& payload, const Rig& rig,
                                               Written* written = nullptr, const std::string& expected = {});
  // An upload's character found in memory: true once its cache file is whole (checked, or written anew from the
  // rig); false when the rig could not give back the paths it was built with (then it is dropped).
  bool KeepFile(const std::shared_ptr<const Entry>& entry, const CharacterData& data);
  // The checked parts of the cache file; nullopt when there is none, or it is corrupt (then it is removed).
  std::optional<CacheFile> ReadFile(const std::string& id);
  // The cache file open as `fd` is whole (just checked, or written): Verified says so until it changes.
  void Remember(const std::string& id, int fd);
  // Whether the cache file is the one last checked or written, unchanged since.
  bool Verified(const std::string& id);

  StoreOptions options_;
  mutable std::mutex mutex_;
  std::list<std::string> lru_;  // most recent first
  struct Slot {
    std::shared_ptr<const Entry> entry;
    std::list<std::string>::iterator position;
  };
  std::unordered_map<std::string, Slot> entries_;
  void Erase(std::unordered_map<std::string, Slot>::iterator it);  // out of memory; the caller holds mutex_
  std::unordered_map<std::string, std::shared_ptr<PendingBuild>> building_;
  // A file's identity and version: its inode, size and modification time.
  struct FileStamp {
    std::uint64_t device = 0, inode = 0;
    std::int64_t size = 0, seconds = 0, nanoseconds = 0;
    static FileStamp Of(const struct stat& status) {
      return {static_cast<std::uint64_t>(status.st_dev), static_cast<std::uint64_t>(status.st_ino),
              static_cast<std::int64_t>(status.st_size), static_cast<std::int64_t>(status.st_mtim.tv_sec),
              static_cast<std::int64_t>(status.st_mtim.tv_nsec)};
    }
    bool operator==(const FileStamp&) const = default;
  };
  // Cache files checked in full (checksums and id) since they last changed: read, or written, by this store.
  std::unordered_map<std::string, FileStamp> verified_;
  StoreStats stats_;
  std::atomic<std::int64_t> write_failures_{0};  // StoreStats::write_failures (counted without the lock)
  std::unique_ptr<SolverPool> builds_;  // last: its threads end before the rest goes
};

class CharacterStore::PendingBuild {
 public:
  PendingBuild(std::string id, bool from_file, std::string name);
  const std::string& id() const { return id_; }
  const std::string& name() const { return name_; }  // empty for a rebuild from the cache directory
  BuildProgress progress() const;
  using Done = std::function<void(const std::shared_ptr<const Entry>& entry, std::exception_ptr error)>;
  // `done` runs once the build has ended: at once, on this thread, if it has; else on the build's thread, after
  // the build (keep it short). With the entry (null when a rebuild found its file gone or corrupt) or the error.
  void OnDone(Done done);

 private:
  friend class CharacterStore;
  void Report(const RigBuildProgress& progress);
  void End(std::shared_ptr<const Entry> entry, std::exception_ptr error);  // tells the waiters, once

  const std::string id_, name_;
  const std::chrono::steady_clock::time_point created_;
  mutable std::mutex mutex_;
  BuildProgress progress_;
  double paths_began_ms_ = -1.0;  // when the paths stage began (the estimate's origin)
  std::list<Wants> waiters_;      // Found::waiter erases its own
  std::vector<Done> done_;
  bool ended_ = false;
  std::shared_ptr<const Entry> entry_;
  std::exception_ptr error_;
  bool deleted_ = false;  // a Delete came while it built: do not keep the result (the store's mutex_)
};

}  // namespace springblend::server
