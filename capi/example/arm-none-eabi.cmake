# CMake toolchain file: Debian's gcc-arm-none-eabi and libnewlib-arm-none-eabi, for a Cortex-M7
# with its double-precision FPU (the static library is built for thumbv7em-none-eabihf with
# -C target-cpu=cortex-m7: the same ABI, hard float).
set(CMAKE_SYSTEM_NAME Generic)
set(CMAKE_SYSTEM_PROCESSOR cortex-m7)
set(CMAKE_C_COMPILER arm-none-eabi-gcc)
set(CMAKE_ASM_COMPILER arm-none-eabi-gcc)
set(CMAKE_TRY_COMPILE_TARGET_TYPE STATIC_LIBRARY)

set(GOMATCH_CPU_FLAGS "-mcpu=cortex-m7 -mthumb -mfpu=fpv5-d16 -mfloat-abi=hard")
set(CMAKE_C_FLAGS_INIT "${GOMATCH_CPU_FLAGS} -ffunction-sections -fdata-sections")
set(CMAKE_ASM_FLAGS_INIT "${GOMATCH_CPU_FLAGS}")
set(CMAKE_EXE_LINKER_FLAGS_INIT "${GOMATCH_CPU_FLAGS}")
# The Rust target of the static library that matches these flags.
set(GOMATCH_RUST_TARGET thumbv7em-none-eabihf)
set(GOMATCH_RUST_FLAGS "-C target-cpu=cortex-m7")
set(GOMATCH_RUST_FEATURES "arm-fma,arm-dsp")
