// A host application in miniature: dlopens a plug-in (plugin.cc, a MODULE library) as Maya or Houdini load theirs
// and runs it.   plugin_host PLUGIN.so ADDRESS MESH_DIR VERSION
#include <dlfcn.h>

#include <cstdio>

int main(int argc, char** argv) {
  if (argc != 5) {
    std::fprintf(stderr, "usage: plugin_host PLUGIN.so ADDRESS MESH_DIR VERSION\n");
    return 2;
  }
  void* plugin = dlopen(argv[1], RTLD_NOW | RTLD_LOCAL);
  if (plugin == nullptr) {
    std::fprintf(stderr, "plugin_host: %s\n", dlerror());
    return 1;
  }
  using Run = int (*)(const char*, const char*, const char*);
  const auto run = reinterpret_cast<Run>(dlsym(plugin, "springblend_plugin_run"));
  if (run == nullptr) {
    std::fprintf(stderr, "plugin_host: no springblend_plugin_run in %s\n", argv[1]);
    return 1;
  }
  const int failures = run(argv[2], argv[3], argv[4]);
  dlclose(plugin);
  std::printf("plugin_host: %d failures\n", failures);
  return failures == 0 ? 0 : 1;
}
