// Which instruction set the fast paths are compiled for. Every SIMD loop of the ops has a plain
// C++ reference beside it (`*_scalar`) that also does the ends of rows the vector loop leaves;
// the library picks the AVX2 one when it is compiled in (-march=x86-64-v3, the default) and not
// switched off at run time (QUIETFRAME_OPS_SIMD=0, see simd_enabled()).
#pragma once

#if defined(__AVX2__) && defined(__FMA__)
#include <immintrin.h>
#define QF_HAVE_AVX2 1
#else
#define QF_HAVE_AVX2 0
#endif
