# Every dependency comes from Debian 12's archive (deploy/install-deps.sh installs them).
find_package(Eigen3 3.4 REQUIRED NO_MODULE)
find_package(OpenMesh REQUIRED)
find_package(TBB REQUIRED)
find_package(spdlog REQUIRED)
find_package(fmt REQUIRED)
find_package(CLI11 REQUIRED)
find_package(nlohmann_json 3.10 REQUIRED)
find_package(CGAL 5.5 REQUIRED)
find_package(Protobuf REQUIRED)
find_package(gRPC CONFIG REQUIRED)
find_package(OpenSSL REQUIRED)


# CHOLMOD (SuiteSparse 5.x ships no CMake config in Debian 12).
find_path(CHOLMOD_INCLUDE_DIR cholmod.h PATH_SUFFIXES suitesparse REQUIRED)
find_library(CHOLMOD_LIBRARY cholmod REQUIRED)
find_library(SUITESPARSE_CONFIG_LIBRARY suitesparseconfig REQUIRED)
find_package(BLAS REQUIRED)
find_package(LAPACK REQUIRED)
add_library(springblend_cholmod INTERFACE)
target_include_directories(springblend_cholmod SYSTEM INTERFACE ${CHOLMOD_INCLUDE_DIR})
target_link_libraries(springblend_cholmod INTERFACE
  ${CHOLMOD_LIBRARY} ${SUITESPARSE_CONFIG_LIBRARY} ${LAPACK_LIBRARIES} ${BLAS_LIBRARIES})

# TetGen 1.5 (libtet1.5-dev): a bare header and library; the library is built with TETLIBRARY.
find_path(TETGEN_INCLUDE_DIR tetgen.h REQUIRED)
find_library(TETGEN_LIBRARY tet REQUIRED)
add_library(springblend_tetgen INTERFACE)
target_include_directories(springblend_tetgen SYSTEM INTERFACE ${TETGEN_INCLUDE_DIR})
target_compile_definitions(springblend_tetgen INTERFACE TETLIBRARY)
target_link_libraries(springblend_tetgen INTERFACE ${TETGEN_LIBRARY})
