/* The compiled loops of _kernels.c for the x86-64-v3 instruction-set level (setup.py compiles this file
 * with -march=x86-64-v3); shearfit.engine.kernel imports it where the CPU runs that level. */
#define KERNEL_MODULE _kernels_v3
#define KERNEL_LEVEL "x86-64-v3 (AVX2)"
#include "_kernels.c"
