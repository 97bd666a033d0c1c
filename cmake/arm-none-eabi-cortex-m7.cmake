# Toolchain for the car-side runtime on a Cortex-M7 (bare metal, hard float, newlib).
# Only the libraries are built (no host tools, no tests): the check is that the portable
# core compiles warning-free with -Werror for the embedded target.
set(CMAKE_SYSTEM_NAME Generic)
set(CMAKE_SYSTEM_PROCESSOR cortex-m7)
set(CMAKE_C_COMPILER arm-none-eabi-gcc)
set(CMAKE_TRY_COMPILE_TARGET_TYPE STATIC_LIBRARY)
set(CMAKE_C_FLAGS_INIT "-mcpu=cortex-m7 -mthumb -mfpu=fpv5-d16 -mfloat-abi=hard -ffunction-sections -fdata-sections")
set(DDYN_BUILD_TESTS OFF CACHE BOOL "" FORCE)
set(DDYN_BUILD_TOOLS OFF CACHE BOOL "" FORCE)
