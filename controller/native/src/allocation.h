/* Torque allocation (Tt, Delta M) -> wheel torques T1..T4 (1 FL, 2 FR, 3 RL, 4 RR), N m.
 * Python reference: controller/core/allocation.py (TorqueAllocator, whose operation order
 * this follows).
 *
 * Eq. 16: Tt = T1 + T2 + T3 + T4, dM = T2 + T4 - T1 - T3 (+dM turns the car left).
 * Motor limit |Ti| <= lim_i = min(T_peak, P_peak / |w_i|) (T_peak for a non-finite or
 * zero wheel speed w_i, rad/s). Side capacities C_L = lim1 + lim3, C_R = lim2 + lim4.
 * Infeasible (Tt, dM): dM is kept, Tt yields: dM <- clip(dM, +-(C_L + C_R)),
 * Tt <- clip(Tt, [max(-2 C_R - dM, dM - 2 C_L), min(2 C_R - dM, dM + 2 C_L)]); a
 * non-finite Tt or dM reads as 0. Front/rear split of each side proportional to the
 * estimated normal loads (or equal), saturating one wheel into the other. */
#ifndef RH_ALLOCATION_H
#define RH_ALLOCATION_H

#include <stdint.h>

#include "rh_params.h"
#include "rh_real.h"

#define RH_ALLOC_SPLIT_NORMAL_LOAD 0 /* AllocationConfig.split = "normal_load" */
#define RH_ALLOC_SPLIT_EQUAL 1       /* AllocationConfig.split = "equal" */
#define RH_ALLOC_G 9.81              /* gravity used for the static loads, m/s^2 */

/* Python: AllocationConfig. */
typedef struct {
  int split;             /* RH_ALLOC_SPLIT_NORMAL_LOAD or RH_ALLOC_SPLIT_EQUAL */
  double fz_floor_frac;  /* floor of a wheel load estimate / its static load, - */
  double acc_clip;       /* |ax|, |ay| clip for the load estimate, m/s^2 */
  double cycle_s;        /* time between two allocations (the communication cycle), s */
} rh_alloc_config_t;

typedef struct {
  /* Parameters in working precision (the kernel's prm vector). */
  real_t peak_torque;    /* T_peak per motor, N m */
  real_t peak_power;     /* P_peak per motor, W */
  real_t acc_clip;       /* m/s^2 */
  real_t mass;           /* kg */
  real_t wheelbase;      /* lf + lr, m */
  real_t cg_height;      /* m */
  real_t track;          /* m */
  real_t lf;             /* m */
  real_t lr;             /* m */
  real_t fzf_static;     /* static front axle load m g lr / L, N */
  real_t fzr_static;     /* static rear axle load m g lf / L, N */
  real_t fz_floor_frac;  /* - */
  real_t rate_step;      /* motor torque rate x cycle, N m per allocation (0 = no limit) */
  int split;             /* RH_ALLOC_SPLIT_* */
  /* State. */
  real_t limits[4];      /* motor limits last computed, N m */
  real_t out[4];         /* wheel torques of the last allocate, N m */
  real_t tt_applied;     /* realised Tt of the last allocate, N m */
  real_t dm_applied;     /* realised dM of the last allocate, N m */
  real_t prev[4];        /* torques of the previous allocate (the rate limit's memory), N m */
  int64_t rate_limited_calls; /* allocations in which a wheel was held back by the rate */
} rh_alloc_t;

/* Parameters from the vehicle (static loads computed in double, then rounded);
 * limits = T_peak, out = 0, tt/dm_applied = 0, prev = 0. */
void rh_alloc_init(rh_alloc_t *a, const rh_vehicle_t *veh, const rh_alloc_config_t *cfg);

/* Forget the previous torques (the motors start from zero) and the rate counter. */
void rh_alloc_reset(rh_alloc_t *a);

/* a->limits (4,) N m at wheel speeds ws (4,) rad/s. */
void rh_alloc_motor_limits(rh_alloc_t *a, const real_t ws[4]);

/* motor limits into a->limits (so a following allocate may pass limits_current = 1),
 * then |dM| available at zero pedal torque: 2 min(C_L, C_R), N m. */
real_t rh_alloc_dm_capacity(rh_alloc_t *a, const real_t ws[4]);

/* Front share of the left and right side torque from normal-load estimates (0.5, 0.5
 * with the equal split); ax, ay in m/s^2 (non-finite reads as 0). */
void rh_alloc_front_share(const rh_alloc_t *a, real_t ax, real_t ay, real_t *sl, real_t *sr);

/* Wheel torques (4,) N m for Tt N m and dM N m, ax, ay m/s^2 (load estimate), wheel
 * speeds ws (4,) rad/s. limits_current != 0: a->limits were just computed for ws (not
 * recomputed; ws is not read). With a motor torque rate, every wheel then moves at most
 * rate_step from its previous torque (the motor limit first: a limit that fell cuts at
 * once). Writes torques and a->out, sets a->tt_applied and a->dm_applied to the realised
 * (Tt, dM). torques may be a->out. */
void rh_alloc_allocate(rh_alloc_t *a, real_t tt, real_t dm, real_t ax, real_t ay,
                       const real_t ws[4], int limits_current, real_t torques[4]);

/* sizeof(rh_alloc_t), sizeof(rh_alloc_config_t), sizeof(rh_vehicle_t), bytes (layout
 * checks of bindings). */
void rh_alloc_sizes(int out[3]);

#endif /* RH_ALLOCATION_H */
