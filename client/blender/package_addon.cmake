# cd STAGE && cmake -DADDON_DIR=... -DCLIENT_DIR=... -DSTAGE=... -DZIP=... -P package_addon.cmake
# Stages springblend_blender/ (the add-on) with the client package under springblend_blender/vendor/ and zips
# it, leaving out byte-code caches.
file(REMOVE_RECURSE ${STAGE}/springblend_blender)
file(COPY ${ADDON_DIR}/ DESTINATION ${STAGE}/springblend_blender PATTERN __pycache__ EXCLUDE)
file(COPY ${CLIENT_DIR} DESTINATION ${STAGE}/springblend_blender/vendor PATTERN __pycache__ EXCLUDE)
file(REMOVE ${ZIP})
file(ARCHIVE_CREATE OUTPUT ${ZIP} PATHS springblend_blender FORMAT zip)
