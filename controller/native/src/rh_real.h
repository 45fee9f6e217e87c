/* Working precision of the controller core: real_t is double, or float with -DRH_FLOAT32.
 * Every module includes this header and uses the RH_* maths macros, so one source builds
 * in both precisions (host float64/float32, Cortex-M4F float32). */
#ifndef RH_REAL_H
#define RH_REAL_H

#include <math.h>

#include <float.h>

#ifdef RH_FLOAT32
typedef float real_t;
#define RH_EPS FLT_EPSILON
#define RH_R(x) ((real_t)(x))
#define RH_TANH tanhf
#define RH_ATANH atanhf
#define RH_SQRT sqrtf
#define RH_FABS fabsf
#define RH_EXP expf
#define RH_ATAN2 atan2f
#define RH_ATAN atanf
#define RH_SIN sinf
#define RH_COS cosf
#define RH_TAN tanf
#define RH_FMIN fminf
#define RH_FMAX fmaxf
#else
typedef double real_t;
#define RH_EPS DBL_EPSILON
#define RH_R(x) ((real_t)(x))
#define RH_TANH tanh
#define RH_ATANH atanh
#define RH_SQRT sqrt
#define RH_FABS fabs
#define RH_EXP exp
#define RH_ATAN2 atan2
#define RH_ATAN atan
#define RH_SIN sin
#define RH_COS cos
#define RH_TAN tan
#define RH_FMIN fmin
#define RH_FMAX fmax
#endif

/* isfinite for both precisions (C99 <math.h> macro). */
#define RH_FINITE(x) (isfinite(x))

static inline real_t rh_clip(real_t v, real_t lo, real_t hi) {
  return v < lo ? lo : (v > hi ? hi : v);
}

#endif /* RH_REAL_H */
