# CMake toolchain file: bare-metal Arm (arm-none-eabi GCC), Cortex-M4 by default.
#
#   cmake -S runtime_c -B build/cm4 -DCMAKE_TOOLCHAIN_FILE=runtime_c/cmake/arm-none-eabi.cmake
#   cmake -S runtime_c -B build/cm4f -DCMAKE_TOOLCHAIN_FILE=... -DFBG_ARM_FLAGS="-mcpu=cortex-m4 -mthumb -mfpu=fpv4-sp-d16 -mfloat-abi=hard"
#
# FBG_ARM_FLAGS picks the core and ABI (default: Cortex-M4, soft float, as target.mk's
# target-lib); add -DFBG_USE_DSP=ON for the DSP-extension kernels. Set
# ARM_NONE_EABI_PREFIX when the toolchain is not on PATH (e.g. /opt/gcc-arm/bin/arm-none-eabi-).
set(CMAKE_SYSTEM_NAME Generic)
set(CMAKE_SYSTEM_PROCESSOR arm)

if(NOT DEFINED ARM_NONE_EABI_PREFIX)
  set(ARM_NONE_EABI_PREFIX "arm-none-eabi-")
endif()
set(CMAKE_C_COMPILER "${ARM_NONE_EABI_PREFIX}gcc")
set(CMAKE_CXX_COMPILER "${ARM_NONE_EABI_PREFIX}g++")
set(CMAKE_ASM_COMPILER "${ARM_NONE_EABI_PREFIX}gcc")
set(CMAKE_AR "${ARM_NONE_EABI_PREFIX}ar" CACHE FILEPATH "archiver")
set(CMAKE_RANLIB "${ARM_NONE_EABI_PREFIX}ranlib" CACHE FILEPATH "ranlib")

# No OS to link a test executable against: compiler checks build a static library instead.
set(CMAKE_TRY_COMPILE_TARGET_TYPE STATIC_LIBRARY)

set(FBG_ARM_FLAGS "-mcpu=cortex-m4 -mthumb -mfloat-abi=soft" CACHE STRING "core and ABI flags")
set(CMAKE_C_FLAGS_INIT "${FBG_ARM_FLAGS}")
set(CMAKE_CXX_FLAGS_INIT "${FBG_ARM_FLAGS}")

set(CMAKE_FIND_ROOT_PATH_MODE_PROGRAM NEVER)
set(CMAKE_FIND_ROOT_PATH_MODE_LIBRARY ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_INCLUDE ONLY)
set(CMAKE_FIND_ROOT_PATH_MODE_PACKAGE ONLY)
