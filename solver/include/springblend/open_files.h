// How many cache files the process keeps open for rigs to read their target paths from
// (RigBuildControl::precomputed_file and persist). Each rig whose paths stay in a file reads them through one
// descriptor; a process holding many rigs would otherwise hold as many descriptors, until opening anything else
// (a connection, a cache file being written) fails.
#pragma once

namespace springblend {

// At most `limit` such files open at once, process-wide (0, the default: no bound). Past it, the least recently
// read file whose reads are over is closed, and opened again by its name when a frame next reads it: without
// following links or blocking, and only if the name is still the same file (its device and inode), else that
// read throws DataLossError naming the file (it was removed, or another file renamed over its name, meanwhile).
// Files without a name (a build's spool) are never closed and not counted. Thread-safe.
void SetOpenPathFileLimit(int limit);
// How many are open now.
int OpenPathFiles();

}  // namespace springblend
