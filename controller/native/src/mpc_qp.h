/* Linearised-per-step NMPC as a condensed QP solved by OSQP's generated solver (Python
 * reference: controller/core/mpc/qp.py, LinearizedMpc). Decision z = Delta M / u_scale over
 * the horizon; outputs y = [wr, beta] per stage. */
#ifndef RH_MPC_QP_H
#define RH_MPC_QP_H

#include <stdint.h>

#include "rh_params.h"
#include "rh_qpws.h"

#ifndef RH_N_MAX
#define RH_N_MAX 10          /* longest horizon this build supports (osqp_gen.N_MAX) */
#endif
#define RH_NX 3

/* QpStatus of controller/core/interfaces.py */
#define RH_QP_SOLVED 0
#define RH_QP_SOLVED_INACCURATE 1
#define RH_QP_MAX_ITER 2
#define RH_QP_FAILED 3
#define RH_QP_NOT_RUN 4
#define RH_QP_FALLBACK 5

typedef struct {
  int horizon;                   /* N, stages (1..RH_N_MAX) */
  double q_yaw[RH_N_MAX];        /* per stage, on (rad/s)^2 */
  double r_beta[RH_N_MAX];       /* per stage, on rad^2 */
  double input_reg;              /* lambda per (kN m)^2 */
  double rate_limit_nm_per_s;    /* |dDeltaM/dt| bound, N m/s (0 = off) */
  int sqp_iterations;            /* linearise+solve rounds per step (1..10) */
  double fallback_decay;         /* Delta M <- decay * previous on failure, - */
  double u_scale;                /* N m per decision unit */
  double v_min;                  /* speed floor of the beta linearisation, m/s */
  double delta_m_max_nm;         /* cap on |Delta M|, N m (0 = motor capacity) */
  /* OSQP settings that steer the iteration (the rest is fixed by the generated template) */
  int max_iter;
  double eps_abs, eps_rel, eps_prim_inf, eps_dual_inf, alpha;
  int check_termination, warm_starting, adaptive_rho_interval, scaled_termination;
  double adaptive_rho_tolerance, adaptive_rho_fraction;
  double delta_rate_weight;      /* lambda_D per (kN m)^2 of Delta M increment (0 = off) */
  int envelope;                  /* the envelope shape: 2 slacks, 4N envelope rows (0/1) */
  double env_lr_m;               /* CG to rear axle for the rear slip rows, m */
  double env_lead_s;             /* look-ahead on beta in the rear slip rows, s */
  double env_slack_linear;       /* exact penalty per unit slack */
  double env_slack_quad;         /* quadratic penalty per unit slack^2 */
  double env_v_min_mps;          /* Vx floor of the look-ahead term, m/s */
  double delta_accel_weight;     /* lambda_2 per (kN m)^2 of Delta M second difference (0 = off) */
  int unconstrained_first;       /* the cost's minimiser without OSQP when no row binds (0/1) */
  int scaling;                   /* OSQP's Ruiz passes per data update (>= 1) */
} rh_qp_config_t;

/* Prediction model callback: rollout xbar (n+1, nx) and Jacobians A (n, nx, nx), B (n, nx)
 * from x0 along ubar (n) N m. */
typedef void (*rh_rollout_fn)(const void *model, const real_t x0[RH_NX], const real_t *ubar,
                              int n, const rh_ctx_t *ctx, real_t *xbar, real_t *A, real_t *B);

#define RH_NV_MAX (RH_N_MAX + 2)       /* decisions: Delta M stages + 2 slacks */
#define RH_M_MAX (6 * RH_N_MAX + 2)    /* rows of the envelope shape */
#define RH_AX_MAX (RH_N_MAX + 2 * RH_N_MAX - 1 + 4 * RH_N_MAX * RH_N_MAX + 4 * RH_N_MAX + 2)

typedef struct {
  rh_qp_config_t cfg;
  int N, m, rate, env, nv, nnz_a;  /* env: the envelope shape; nv decisions; nnz_a of A */
  /* constants in the working precision */
  real_t u_scale, v_min, fallback_decay;  /* N m, m/s, - */
  real_t reg[RH_N_MAX * RH_N_MAX]; /* 2 lambda I + 2 lambda_D D'D + 2 lambda_2 D2'D2, row-major */
  OSQPFloat rate_step;             /* rate bound per period, decision units */
  real_t wdiag[2 * RH_N_MAX];
  /* linearisation and QP data (decision units) */
  real_t xbar[(RH_N_MAX + 1) * RH_NX];
  real_t ubar[RH_N_MAX];          /* nominal / accepted input, N m */
  real_t A[RH_N_MAX * RH_NX * RH_NX];
  real_t B[RH_N_MAX * RH_NX];
  real_t S[RH_N_MAX * RH_NX * RH_N_MAX];
  real_t G[2 * RH_N_MAX * RH_N_MAX];
  real_t ybar[2 * RH_N_MAX];
  real_t yd[2 * RH_N_MAX];
  real_t Pd[RH_N_MAX * RH_N_MAX];
  real_t Px[RH_N_MAX * (RH_N_MAX + 1) / 2];
  real_t q[RH_N_MAX];
  real_t lb[RH_N_MAX], ub[RH_N_MAX], z[RH_N_MAX];
  real_t sol[RH_N_MAX];           /* last accepted solution, N m */
  real_t b_prev[RH_NX];           /* d x_{i+1} / d Delta M_{i-1} (dead-time models) */
  int has_b_prev;
  /* OSQP data in OSQP's own precision (OSQPFloat: double on the host, float with
   * OSQP_USE_FLOAT on the microcontroller) */
  OSQPFloat px64[RH_N_MAX * (RH_N_MAX + 1) / 2 + 2];
  OSQPFloat q64[RH_NV_MAX];
  OSQPFloat l[RH_M_MAX], u[RH_M_MAX];
  OSQPFloat ax[RH_AX_MAX];        /* A's values in CSC order (envelope shape) */
  OSQPFloat aenv[4 * RH_N_MAX * RH_N_MAX]; /* the envelope rows' Delta M block, row-major */
  OSQPFloat y_last[RH_M_MAX];     /* OSQP's last dual iterate */
  OSQPFloat slack[2];             /* last (s_r, s_alpha), fractions of the envelope bounds */
  OSQPFloat zprev;                /* applied Delta M of the current solve, decision units */
  OSQPFloat zprev2;               /* and of the solve before it */
  int has_y_last;
  OSQPFloat lo_last, hi_last;     /* box of the last bounds update, decision units */
  int bounds_dirty;
  /* counters */
  int64_t last_iterations, worst_iterations, max_iter_hits, fallbacks;
  int64_t unconstrained_solves;   /* QPs solved without OSQP (unconstrained_first) */
  int last_status;
  rh_qpws_t ws;                   /* OSQP's workspace of this shape */
} rh_qp_t;

/* 0 on success; -1 invalid config; -2 no generated solver for this shape in this build. */
int rh_qp_init(rh_qp_t *qp, const rh_qp_config_t *cfg, double ts_s);
/* Forget warm starts and the previous solution (fresh OSQP workspace). */
void rh_qp_reset(rh_qp_t *qp);
/* The stable-handling envelope of one step (envelope shape): active 0 = rows inactive;
 * r_max rad/s, a_max rad, ay m/s^2 (measured). */
typedef struct {
  int active;
  double r_max, a_max, ay;
} rh_qp_env_t;

/* One MPC step from x0 with held references (wr_d rad/s, beta_d rad) and box [dm_min,
 * dm_max] N m; dm_prev: Delta M applied over the last period, N m; env: the envelope (NULL
 * or ignored without the envelope shape). Writes *dm (N m), *status, *iterations,
 * *fallback. */
void rh_qp_solve(rh_qp_t *qp, rh_rollout_fn rollout, const void *model, const real_t x0[RH_NX],
                 const rh_ctx_t *ctx, real_t yaw_ref, real_t beta_ref, real_t dm_min,
                 real_t dm_max, real_t dm_prev, const rh_qp_env_t *env, real_t *dm,
                 int *status, int *iterations, int *fallback);
/* Warm start OSQP from (x, y) (decision units; NULL = unchanged). */
void rh_qp_warm_start(rh_qp_t *qp, const OSQPFloat *x, const OSQPFloat *y);
/* Relocating copy (the OSQP workspace holds internal pointers). */
void rh_qp_copy(rh_qp_t *dst, const rh_qp_t *src);

#endif /* RH_MPC_QP_H */
