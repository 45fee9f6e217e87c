/* rhonn-tv controller core: the whole MPC step of nmpc-rhonn, nmpc-mf and lmpc and the
 * passive allocation, in C99 with static memory (Python reference: controller/core,
 * MpcController / PassiveController; the numpy classes are the oracle of the back-to-back
 * tests).
 *
 * Usage (static memory; the caller owns the state):
 *     static rh_ctrl_t ctrl;
 *     rh_ctrl_init(&ctrl, &config);          once (config from the generated tables)
 *     rh_ctrl_step(&ctrl, &in, &out);        every MPC period Ts
 *     rh_ctrl_allocate_only(&ctrl, &in, &out) between MPC periods (held Delta M)
 * Units: SI (m, s, rad, N, N m); wheel order 1 FL, 2 FR, 3 RL, 4 RR; ISO 8855 signs. */
#ifndef RHONN_CORE_H
#define RHONN_CORE_H

#include "allocation.h"
#include "bicycle.h"
#include "grip.h"
#include "grip_demand.h"
#include "linear_refs.h"
#include "mpc_qp.h"
#include "refs.h"
#include "rhonn_model.h"
#include "seven_dof.h"

#define RH_CTRL_NMPC_RHONN 0
#define RH_CTRL_NMPC_MF 1
#define RH_CTRL_LMPC 2
#define RH_CTRL_PASSIVE 3

/* Decoded bus values of one step (Python: ControllerInputs). */
typedef struct {
  real_t swa_rad;          /* steering-wheel angle, rad (+ left) */
  real_t accel_pedal;      /* 0..1 */
  real_t brake_pedal;      /* 0..1 */
  real_t yaw_rate;         /* rad/s */
  real_t ax, ay;           /* body accelerations, m/s^2 */
  real_t wheel_speeds[4];  /* rad/s */
  real_t vx, vy;           /* estimated body velocities, m/s */
  int stab_enable;         /* stability function enabled */
  int sensors_valid;       /* all frames valid and fresh */
  int wheel_speeds_usable; /* 0: the wheel-speed array could not be read (zeros, invalid) */
} rh_inputs_t;

/* Result of one step (Python: ControllerOutputs). */
typedef struct {
  real_t torques[4];          /* wheel torque commands, N m */
  real_t total_torque;        /* driver's Tt, N m */
  real_t delta_m;             /* realised Delta M, N m */
  real_t yaw_rate_ref;        /* rad/s */
  real_t vy_ref;              /* m/s */
  real_t beta_ref;            /* rad */
  int qp_status;              /* RH_QP_* */
  int qp_iterations;          /* OSQP iterations this step */
  int fallback;               /* the defined fallback Delta M was used */
  real_t model_prediction[3]; /* one-step model estimate [vx, vy, r] (NaN if none) */
} rh_outputs_t;

typedef struct {
  int kind;                   /* RH_CTRL_* */
  double ts_s;                /* MPC period Ts, s */
  double v_min_mps;           /* below this speed Delta M = 0, m/s */
  rh_vehicle_t vehicle;
  rh_alloc_config_t alloc;
  rh_qp_config_t qp;          /* MPCs */
  rh_rhonn_config_t rhonn;    /* nmpc-rhonn */
  double rhonn_w0[RH_NW];     /* nmpc-rhonn initial weights (3, 15), state units */
  rh_refs_config_t refs;      /* nmpc-rhonn reference design */
  rh_seven_dof_config_t seven_dof; /* nmpc-mf */
  double bicycle_h_max_s;     /* lmpc sub-step bound, s */
  rh_grip_config_t grip;      /* [grip] */
  rh_handling_config_t handling; /* [handling] */
  int grip_demand;            /* the yaw reference is the grip-limited demand (0/1) */
  int envelope;               /* envelope rows in this controller's QP (0/1; = qp.envelope) */
  rh_yaw_gain_config_t rhonn_dm_gain; /* nmpc-rhonn: [rhonn] dm_gain_* (learned Delta M
                                       * effectiveness; dm_gain_p0 = 0: off) */
} rh_ctrl_config_t;

typedef struct {
  /* what the step reads of the configuration (the rest is used at init only: the state
   * does not hold a copy of it, which on a microcontroller would be RAM for flash data) */
  int kind;                   /* RH_CTRL_* */
  int grip_demand;            /* the yaw reference is the grip-limited demand (0/1) */
  int envelope;               /* envelope rows in the QP (0/1) */
  double env_v_min;           /* [handling] v_min_mps: the envelope's lowest speed, m/s */
  double env_yaw_margin;      /* [handling] yaw_margin, - */
  double env_rear_slip_factor; /* [handling] rear_slip_factor, - */
  int fixed_point_share;      /* [handling] fixed_point_share > 0 (0/1) */
  /* per-step constants in the working precision */
  real_t peak_torque;         /* per motor, N m */
  real_t steering_ratio;      /* - */
  real_t v_min;               /* m/s */
  real_t dm_cap;              /* cap on |Delta M|, N m (0 = motor capacity) */
  rh_outputs_t out;
  rh_alloc_t alloc;
  rh_ctx_t ctx;
  real_t x[RH_NX];            /* measured state [vx, vy, r] */
  real_t dm_held;             /* last MPC command, N m */
  real_t dm_prev;             /* last applied Delta M, N m */
  real_t confidence;          /* last model confidence (scales the Delta M box), - */
  rh_grip_t grip;             /* grip estimate (updated when grip_demand or envelope) */
  rh_grip_demand_t gdemand;   /* grip-limited demand (grip_demand) */
  double slip_per_mu;         /* 3 m g lf / (L |Cr|): atan argument per unit mu, - */
  int64_t steps, invalid_steps;
  union {
    struct {
      rh_rhonn_model_t model;
      rh_refs_t refs;            /* the configured RHONN reference design */
      rh_linear_refs_t linear;   /* [references] kind = "linear" (ablation) */
      int use_linear;
    } rhonn;
    struct { rh_seven_dof_t model; rh_linear_refs_t refs; } mf;
    struct { rh_bicycle_t model; rh_linear_refs_t refs; } lmpc;
  } u;
  rh_qp_t qp;                 /* last: its OSQP workspace holds internal pointers */
} rh_ctrl_t;

/* 0 on success; -1 invalid config; -2 no generated QP solver for this horizon/shape. */
int rh_ctrl_init(rh_ctrl_t *c, const rh_ctrl_config_t *cfg);
/* Cold start: weights, filters, references, warm starts, outputs. */
void rh_ctrl_reset(rh_ctrl_t *c);
/* One MPC period (learning, references, QP, allocation). Never fails on bad numbers. */
void rh_ctrl_step(rh_ctrl_t *c, const rh_inputs_t *in, rh_outputs_t *out);
/* Between MPC periods: re-allocate the held Delta M with the fresh pedal torque. */
void rh_ctrl_allocate_only(rh_ctrl_t *c, const rh_inputs_t *in, rh_outputs_t *out);
/* dst = a copy of src that runs on bit for bit (internal pointers relocated). */
void rh_ctrl_copy(rh_ctrl_t *dst, const rh_ctrl_t *src);
/* sizeof(rh_ctrl_t) and sizeof(rh_ctrl_config_t), bytes (layout checks of bindings). */
void rh_ctrl_sizes(int64_t out[2]);

#endif /* RHONN_CORE_H */
