# cmake --install: headers, libraries, programs and the springblend CMake package, for the parts that were built.
#   bin/springblend-server, bin/springblend            the server and the command line
#   libexec/springblend/springblend-tetgen             the solver's TetGen helper (found from bin/ as ../libexec)
#   include/springblend/...                            geometry.h, version.h, the solver's and the client's API,
#                                                      and the generated springblend/v1 messages
#   lib/libspringblend_*.a, lib/cmake/springblend/     the libraries and springblendConfig.cmake
# A plug-in writes find_package(springblend CONFIG REQUIRED) and links springblend::client or springblend::solver;
# each part's dependencies are found (find_dependency) only when that part is asked for.
include(CMakePackageConfigHelpers)
set(SPRINGBLEND_CMAKE_DIR ${CMAKE_INSTALL_LIBDIR}/cmake/springblend)
set(SPRINGBLEND_INSTALLED_PARTS "")

install(DIRECTORY ${PROJECT_SOURCE_DIR}/geometry/include/ ${SPRINGBLEND_GENERATED_INCLUDE}/
        DESTINATION ${CMAKE_INSTALL_INCLUDEDIR})
install(TARGETS springblend_geometry EXPORT springblendGeometryTargets)
install(EXPORT springblendGeometryTargets NAMESPACE springblend:: DESTINATION ${SPRINGBLEND_CMAKE_DIR})

if(SPRINGBLEND_BUILD_SOLVER)
  list(APPEND SPRINGBLEND_INSTALLED_PARTS solver)
  install(DIRECTORY ${PROJECT_SOURCE_DIR}/solver/include/ DESTINATION ${CMAKE_INSTALL_INCLUDEDIR})
  install(TARGETS springblend_solver springblend_cholmod springblend_mumps EXPORT springblendSolverTargets)
  install(EXPORT springblendSolverTargets NAMESPACE springblend:: DESTINATION ${SPRINGBLEND_CMAKE_DIR})
  install(TARGETS springblend-tetgen DESTINATION ${CMAKE_INSTALL_LIBEXECDIR}/springblend)
endif()

if(SPRINGBLEND_BUILD_CLIENT)
  list(APPEND SPRINGBLEND_INSTALLED_PARTS client)
  install(DIRECTORY ${PROJECT_SOURCE_DIR}/client/include/ DESTINATION ${CMAKE_INSTALL_INCLUDEDIR})
  install(FILES ${SPRINGBLEND_PROTO_HEADERS} DESTINATION ${CMAKE_INSTALL_INCLUDEDIR}/springblend/v1)
  install(TARGETS springblend_client springblend_proto EXPORT springblendClientTargets)
  install(EXPORT springblendClientTargets NAMESPACE springblend:: DESTINATION ${SPRINGBLEND_CMAKE_DIR})
  # The SDK: lib/libspringblend_sdk.so.0 (and its .so link); a plug-in needs no other library of ours.
  list(APPEND SPRINGBLEND_INSTALLED_PARTS sdk)
  install(TARGETS springblend_sdk EXPORT springblendSdkTargets)
  install(EXPORT springblendSdkTargets NAMESPACE springblend:: DESTINATION ${SPRINGBLEND_CMAKE_DIR})
  if(TARGET springblend)
    install(TARGETS springblend)
  endif()
  # The Python client (pure Python plus its generated modules): put share/springblend/python on sys.path.
  install(DIRECTORY ${SPRINGBLEND_PYTHON_DIR}/springblend DESTINATION ${CMAKE_INSTALL_DATADIR}/springblend/python
          PATTERN __pycache__ EXCLUDE)
endif()

if(SPRINGBLEND_BUILD_SERVER)
  install(TARGETS springblend-server)
endif()

configure_package_config_file(${CMAKE_CURRENT_LIST_DIR}/springblendConfig.cmake.in
  ${PROJECT_BINARY_DIR}/springblendConfig.cmake INSTALL_DESTINATION ${SPRINGBLEND_CMAKE_DIR})
# 0.x: a minor version may break the API.
write_basic_package_version_file(${PROJECT_BINARY_DIR}/springblendConfigVersion.cmake
  VERSION ${PROJECT_VERSION} COMPATIBILITY SameMinorVersion)
install(FILES ${PROJECT_BINARY_DIR}/springblendConfig.cmake ${PROJECT_BINARY_DIR}/springblendConfigVersion.cmake
        DESTINATION ${SPRINGBLEND_CMAKE_DIR})
