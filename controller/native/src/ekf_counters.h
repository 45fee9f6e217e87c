/* Diagnostics of the EKF learning guards, shared by both EKF forms (ekf.h, ud_ekf.h).
 * Mirrors controller/core/learning/ekf.py: EkfCounters (monotonic counts since the last
 * reset; same names, same order). */
#ifndef RH_EKF_COUNTERS_H
#define RH_EKF_COUNTERS_H

#include <stdint.h>

typedef struct {
  int64_t updates;      /* accepted updates, - */
  int64_t rejected;     /* skipped: non-finite h or e, or non-finite / non-positive s, - */
  int64_t frozen;       /* learning frozen on request (rh_*_freeze), - */
  int64_t trace_resets; /* per-neuron resets of P to p0 I (trace(P_i) > trace_max), - */
  int64_t eig_repairs;  /* per-neuron eigenvalue floors (standard form only), - */
  int64_t weight_clips; /* accepted updates that had to clip |W| to w_max, - */
} rh_ekf_counters_t;

#endif /* RH_EKF_COUNTERS_H */
