# cmake -DSOURCE_DIR=... -DOUT=... -P write_commit_header.cmake: writes OUT defining GAPS_COMMIT (the short hash of
# SOURCE_DIR's HEAD, "-dirty" when tracked files differ from it; $ENV{GAPS_COMMIT} for a tree without .git),
# leaving OUT untouched when it already says that.
if(DEFINED ENV{GAPS_COMMIT})
  set(commit "$ENV{GAPS_COMMIT}")
else()
  execute_process(COMMAND git rev-parse --short=12 HEAD WORKING_DIRECTORY ${SOURCE_DIR} OUTPUT_VARIABLE commit
    OUTPUT_STRIP_TRAILING_WHITESPACE ERROR_QUIET RESULT_VARIABLE failed)
  if(failed)
    set(commit "unknown")
  else()
    execute_process(COMMAND git status --porcelain --untracked-files=no WORKING_DIRECTORY ${SOURCE_DIR}
      OUTPUT_VARIABLE changes ERROR_QUIET)
    if(NOT changes STREQUAL "")
      string(APPEND commit "-dirty")
    endif()
  endif()
endif()
set(content "#define GAPS_COMMIT \"${commit}\"\n")
set(old "")
if(EXISTS ${OUT})
  file(READ ${OUT} old)
endif()
if(NOT old STREQUAL content)
  file(WRITE ${OUT} "${content}")
endif()
