/* The compiled loops of _kernels.c for the x86-64-v4 instruction-set level (setup.py compiles this file
 * with -march=x86-64-v4); shearfit.engine.kernel imports it where the CPU runs that level. */
#define KERNEL_MODULE _kernels_v4
#define KERNEL_LEVEL "x86-64-v4 (AVX-512)"
#include "_kernels.c"
