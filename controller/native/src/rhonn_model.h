/* RHONN prediction model with online EKF learning (Python reference:
 * controller/core/model/rhonn.py, RhonnModel). States [Vx m/s, Vy m/s, wr rad/s]; inputs
 * Tt N m (in the context), Delta M N m, dw rad (in the context). */
#ifndef RH_RHONN_MODEL_H
#define RH_RHONN_MODEL_H

#include <stdint.h>

#include "ekf.h"
#include "rh_params.h"
#include "rhonn.h"
#include "ud_ekf.h"
#include "yaw_gain.h"

/* 1: the state holds the learned Delta M effectiveness's filter (rh_yaw_gain_t, 1.3 kB in
 * float32); a firmware built for a configuration that leaves it off ([rhonn] dm_gain_p0 = 0)
 * sets 0, and rh_rhonn_model_init_dm_gain then refuses to switch it on. */
#ifndef RH_DM_GAIN
#define RH_DM_GAIN 1
#endif

#define RH_EKF_STANDARD 0
#define RH_EKF_UD 1

typedef struct {
  double mu[RH_NXI];        /* S output scales, - */
  double beta[RH_NXI];      /* S input gains, 1/(m/s), 1/(m/s), 1/(rad/s), 1/rad */
  int increment;            /* 1: increment form (default), 0: literal eq. 17 */
  double dm_dead_time_s;    /* T_d, s */
  double gate_warmup_s;     /* learning-only time before any Delta M, s */
  double gate_tau_s;        /* time constant of the filtered one-step wr error, s */
  double gate_err_lo;       /* filtered RMS wr error with confidence 1, rad/s */
  double gate_err_hi;       /* ... with confidence 0, rad/s (0: gate off) */
  int ekf_form;             /* RH_EKF_STANDARD | RH_EKF_UD */
  rh_ekf_config_t ekf;      /* learning tuning */
} rh_rhonn_config_t;

typedef struct {
  real_t mu[RH_NXI], beta[RH_NXI];
  int increment;
  /* constants (computed in double at init, kept in the working precision) */
  real_t kd_now, kd_prev;   /* gains of Delta M_k and Delta M_{k-1} on wr_{k+1}, (rad/s)/(N m) */
  real_t kd0_now;           /* kd_now at theta = 1 (the nominal car), (rad/s)/(N m) */
  real_t kd0_prev;          /* kd_prev at theta = 1, (rad/s)/(N m) */
  real_t kt_ts;             /* Ts / (m r), (m/s)/(N m) */
  /* model-confidence gate */
  int gate_on;
  real_t gate_a;            /* filter pole per step, - */
  int64_t gate_n;           /* accepted updates before the ramp */
  real_t gate_err_lo, gate_err_hi;  /* rad/s */
  real_t err_ms;            /* filtered mean square one-step wr error, (rad/s)^2 */
  int64_t learn_steps;      /* accepted EKF updates since reset */
  int gate_open;            /* latched */
  /* pending one-step prediction (series-parallel identification) */
  int has_record;
  real_t rec_phi[RH_NPHI];
  real_t rec_chi[3];
  /* learned Delta M effectiveness (yaw_gain.h; off: theta = 1, the nominal gains) */
  int dm_gain_on;           /* 1 when [rhonn] dm_gain_p0 > 0 (rh_rhonn_model_init_dm_gain) */
  real_t theta;             /* the effectiveness in use, - */
  real_t rec_u;             /* the record's known Delta M part at theta = 1, rad/s */
#if RH_DM_GAIN
  rh_yaw_gain_t dm_gain;    /* its joint filter with the yaw row (owns that row when on) */
#endif
  int ekf_form;
  union {
    rh_ekf_t std;           /* ekf_form == RH_EKF_STANDARD */
    rh_ud_ekf_t ud;         /* ekf_form == RH_EKF_UD */
  } f;
} rh_rhonn_model_t;

/* Initialise from the config; w0 (3, 15): initial weights (drawn by the caller). Returns 0,
 * or -1 for an invalid config. */
int rh_rhonn_model_init(rh_rhonn_model_t *m, const rh_rhonn_config_t *cfg,
                        const rh_vehicle_t *p, double ts_s, const real_t w0[RH_NW]);
/* Switch the learned Delta M effectiveness on (cfg->dm_gain_p0 > 0) or leave it off
 * (dm_gain_p0 == 0, theta = 1); call after rh_rhonn_model_init, which leaves it off. Its
 * filter starts from the yaw row of w0 in the model's EKF form. Returns 0, or -1 for an
 * invalid config (negative or non-finite p0, bounds not 0 < min <= 1 <= max; then off). */
int rh_rhonn_model_init_dm_gain(rh_rhonn_model_t *m, const rh_yaw_gain_config_t *cfg);
/* Cold start: weights, covariances, theta = 1, gate; no pending record. */
void rh_rhonn_model_reset(rh_rhonn_model_t *m);
/* The Delta M gains kd_now, kd_prev from theta = the filter's (1 when off), after its state
 * was written from outside (a checkpoint restore). */
void rh_rhonn_model_sync_dm_gain(rh_rhonn_model_t *m);
/* The live weights (3, 15). */
const real_t *rh_rhonn_model_weights(const rh_rhonn_model_t *m);
rh_rhonn_view_t rh_rhonn_model_view(const rh_rhonn_model_t *m);
/* EKF update from the pending record (e = x - chi); frozen (counted) when !learn. Then, with
 * the learned Delta M effectiveness on and the update accepted, its joint filter with e_r:
 * when that accepts too, its yaw-row weights replace the EKF's and theta rescales kd_now and
 * kd_prev. Returns 1 when the weights changed. */
int rh_rhonn_model_observe(rh_rhonn_model_t *m, const real_t x[3], int learn);
/* Confidence in [0, 1] that scales the Delta M box (latches open at 1). */
real_t rh_rhonn_model_confidence(rh_rhonn_model_t *m);
/* out = chi_{k+1} for state x, Delta M dm N m; kept as the record when finite. */
void rh_rhonn_model_record(rh_rhonn_model_t *m, const real_t x[3], real_t dm,
                           const rh_ctx_t *ctx, real_t out[3]);
void rh_rhonn_model_forget(rh_rhonn_model_t *m);
/* Parallel rollout xbar (n+1, 3) from x0 along ubar (n) N m with Jacobians A (n, 3, 3),
 * B (n, 3) in (rad/s)/(N m); b_prev (3): d x_{k+1} / d Delta M_{k-1}. */
void rh_rhonn_model_rollout(const rh_rhonn_model_t *m, const real_t x0[3], const real_t *ubar,
                            int n, const rh_ctx_t *ctx, real_t *xbar, real_t *A, real_t *B);
void rh_rhonn_model_b_prev(const rh_rhonn_model_t *m, real_t b_prev[3]);

#endif /* RH_RHONN_MODEL_H */
