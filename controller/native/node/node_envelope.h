/* Output safety envelope: the last guard on every wheel-torque answer (Python reference:
 * controller/runtime/envelope.py, SafetyEnvelope; its docstring states the limits, their
 * priority and why they cannot conflict with the default parameters).
 *
 * Sees only the four commanded wheel torques (N m, FL FR RL RR), the measured wheel speeds
 * (rad/s), the zero-Delta-M flag and its own previous output, and for ANY doubles (NaN, inf,
 * huge, negative) returns torques that hold, in priority order: finite; |T_i| <= L_i =
 * min(T_peak, P_peak/|w_i|) floored to the torque quantum; left = right per axle when
 * zero_dm (axle torques kept); per-wheel rate; Delta-M rate (Tt kept); Tt kept as far as
 * these allow. A command inside every limit passes bit for bit (the fast path).
 *
 * Computed in double in both builds (also with RH_FLOAT32): the guard's decisions (a clip
 * counted at 1e-6 N m) then match the reference exactly, at a few hundred soft-float
 * operations per 10 ms cycle on a Cortex-M4F. */
#ifndef RH_NODE_ENVELOPE_H
#define RH_NODE_ENVELOPE_H

#include <stdint.h>

/* [envelope] table (controller/config/envelope.toml). */
typedef struct {
  double torque_rate_nm_per_s;  /* per-wheel |dT/dt| bound, N m/s (> 0), default 60000 */
  double delta_m_rate_nm_per_s; /* |dDeltaM/dt| bound, N m/s (> 0), default 180000 */
  double torque_quantum_nm;     /* torque frame resolution the power limit is floored to,
                                   N m (>= 0, 0 = off), default 0.5 */
  double clip_tol_nm;           /* a change below this is not a clip, N m (>= 0), 1e-6 */
} rh_node_envelope_config_t;

/* How often each limit acted (wheel counts per wheel, step counts per call). */
typedef struct {
  int64_t steps;
  int64_t limited_steps; /* steps where a limit (not the zero-Delta-M equalisation) acted */
  int64_t nonfinite_cmd; /* wheels: non-finite command -> 0 */
  int64_t torque_limit;  /* wheels: |T| > T_peak */
  int64_t power_limit;   /* wheels: T_peak >= |T| > P_peak/|w| */
  int64_t rate_limit;    /* wheels: outside the per-wheel rate window */
  int64_t dm_rate_limit; /* steps: commanded Delta M outside the Delta-M rate window */
  int64_t dm_zeroed;     /* steps: zero_dm and the command was not axle-symmetric */
  int64_t tt_reduced;    /* steps: Tt could not be kept */
  int64_t invalid_speed; /* wheels: non-finite w -> T_peak */
  int64_t bad_prev;      /* wheels: previous output non-finite or beyond T_peak */
  int64_t conflicts;     /* a lower-priority limit had to give way (never by default) */
} rh_node_envelope_counters_t;

typedef struct {
  rh_node_envelope_config_t cfg;
  double t_peak;  /* motor peak torque, N m */
  double p_peak;  /* motor peak power, W */
  double dt;      /* call period, s */
  double d_wheel; /* per-wheel change per call, N m */
  double d_dm;    /* Delta-M change per call, N m */
  rh_node_envelope_counters_t counters;
  double limits[4]; /* last computed L_i, N m */
  int last_zeroed;  /* the last call equalised an axle (zero_dm) */
} rh_node_envelope_t;

void rh_node_envelope_default_config(rh_node_envelope_config_t *cfg);
/* 0 on success; -1 for an invalid config (EnvelopeConfig.from_dict's checks) or peak torque,
 * peak power, dt not > 0 (SafetyEnvelope's ValueError): the envelope is then set up with
 * the default config and T_peak = P_peak = 0 (every command is clipped to 0 N m). */
int rh_node_envelope_init(rh_node_envelope_t *e, const rh_node_envelope_config_t *cfg,
                          double peak_torque_nm, double peak_power_w, double dt_s);
/* 1 when the parameters guarantee that the limits never conflict. */
int rh_node_envelope_conflict_free(const rh_node_envelope_t *e);
/* min(T_peak, P_peak/|w|) N m floored to the quantum; non-finite w gives T_peak. */
double rh_node_envelope_wheel_limit(const rh_node_envelope_t *e, double omega_rad_s);
/* Envelope cmd[4] N m given w[4] rad/s and the previous output prev[4] N m; writes out[4]
 * N m (out may be cmd, not prev). Returns 1 when a limit other than the zero-Delta-M
 * equalisation changed the command (FAULT_BITS bit 6). */
int rh_node_envelope_apply(rh_node_envelope_t *e, const double cmd[4],
                           const double wheel_speeds[4], int zero_dm, const double prev[4],
                           double out[4]);

#endif /* RH_NODE_ENVELOPE_H */
