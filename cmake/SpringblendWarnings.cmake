# Warnings and sanitizers live on one INTERFACE target that every springblend target links.
add_library(springblend_build_flags INTERFACE)
target_compile_options(springblend_build_flags INTERFACE
  -Wall -Wextra -Wpedantic -Wshadow -Wnon-virtual-dtor -Wold-style-cast -Wcast-align
  -Woverloaded-virtual -Wimplicit-fallthrough -Wno-missing-field-initializers)
if(SPRINGBLEND_SANITIZE)
  target_compile_options(springblend_build_flags INTERFACE
    -fsanitize=${SPRINGBLEND_SANITIZE} -fno-omit-frame-pointer -fno-sanitize-recover=undefined)
  target_link_options(springblend_build_flags INTERFACE -fsanitize=${SPRINGBLEND_SANITIZE})
endif()
