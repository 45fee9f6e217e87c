/* RHONN steady-state references by the paper's Algorithm 1 (neighbour search on the learned
 * map; eq. 18-20). Python reference: controller/core/references/algorithm1.py
 * (RhonnReferences).
 *
 * Also here, as in algorithm1.py: the configuration of every nmpc-rhonn reference design
 * (rh_refs_config_t = RhonnRefConfig, [references] of default.toml). */
#ifndef RH_REFS_ALG1_H
#define RH_REFS_ALG1_H

#include "rh_params.h"
#include "rh_real.h"
#include "rhonn.h"
#include "slow_weights.h"

/* Compile-time maxima of the bounded search (configs above them are rejected at init). */
#define RH_REFS_GRID_MAX 15    /* grid_n: grid points per axis (odd, >= 3) */
#define RH_REFS_ROUNDS_MAX 16  /* max_rounds: radius rounds */
#define RH_REFS_NEWTON_MAX 16  /* newton_iters: Newton polish steps per round */

/* Reference designs ([references] kind; index in factory.REFERENCE_KINDS). */
enum {
  RH_REFS_ALGORITHM1 = 0, /* RhonnReferences (this module) */
  RH_REFS_INTENT = 1,     /* IntentReferences (refs_intent.h) */
  RH_REFS_BLEND = 2,      /* BlendedReferences(demand="learned") */
  RH_REFS_DEMAND = 3,     /* BlendedReferences(demand="bicycle"), the default */
  RH_REFS_LINEAR = 4      /* LinearReferences: not in this module set (init rejects it) */
};

/* Init results (0 = ok). */
enum {
  RH_REFS_OK = 0,
  RH_REFS_EKIND = -1,    /* unknown kind, or "linear" */
  RH_REFS_EGRID = -2,    /* grid_n even, < 3 or > RH_REFS_GRID_MAX */
  RH_REFS_EROUNDS = -3,  /* max_rounds < 0 or > RH_REFS_ROUNDS_MAX */
  RH_REFS_ENEWTON = -4,  /* newton_iters < 0 or > RH_REFS_NEWTON_MAX */
  RH_REFS_ETIME = -5     /* ts or ay_decay_s not > 0 */
};

/* RhonnRefConfig (algorithm1.py); field order = the dataclass's. */
typedef struct {
  double eta;              /* weight of the wr residual in the cost, (m/s)/(rad/s) */
  double eps_t;            /* threshold on the cost, m/s */
  double rs0_vy;           /* initial search radius in Vy, m/s */
  double rs0_r;            /* initial search radius in wr, rad/s */
  double drs_vy;           /* radius growth per round, m/s */
  double drs_r;            /* radius growth per round, rad/s */
  int grid_n;              /* grid points per axis, odd, 3..RH_REFS_GRID_MAX */
  int max_rounds;          /* radius rounds, 0..RH_REFS_ROUNDS_MAX */
  int newton_iters;        /* Newton polish steps, 0..RH_REFS_NEWTON_MAX */
  double tan_beta_max;     /* tan of the sideslip limit, - (the binding computes it:
                              no double tan in the firmware) */
  double ay_floor;         /* lower bound of a_max, m/s^2 */
  double ay_ceiling;       /* upper bound of a_max, m/s^2 */
  double ay_margin;        /* factor on the |ay| envelope, - */
  double ay_decay_s;       /* envelope decay time constant, s (> 0) */
  double v_min;            /* kinematic references below this speed, m/s */
  double r_kin_factor;     /* bound on wrd relative to Vx dw / L, - */
  double r_band;           /* sign tolerance of wrd, rad/s */
  double ts;               /* call period, s (> 0) */
  int kind;                /* RH_REFS_ALGORITHM1 .. RH_REFS_DEMAND */
  double slow_tau_s;       /* weight copy time constant, s (0: live weights) */
  double intent_lead_s;    /* lead on the steering rate, s (intent/demand) */
  double intent_ay_margin; /* intent/demand |wrd| cap factor on the |ay| envelope, - (0: off) */
  double blend_beta_lo;    /* |beta| where Algorithm 1 starts to take over, rad */
  double blend_beta_hi;    /* |beta| where Algorithm 1 has taken over, rad */
  double guard_beta_rad;   /* sideslip guard |beta| threshold, rad */
  double guard_gain_per_s; /* sideslip guard decay rate of the excess, 1/s (0: no guard) */
  double guard_lead_s;     /* sideslip guard look-ahead on beta_dot, s (0: on beta alone) */
} rh_refs_config_t;

/* Python's builtin max(a, b) / min(a, b) for two floats (NaN handling included: the first
 * argument is kept unless the second compares greater / smaller). */
static inline real_t rh_refs_pymax(real_t a, real_t b) { return b > a ? b : a; }
static inline real_t rh_refs_pymin(real_t a, real_t b) { return b < a ? b : a; }

/* Algorithm 1 generator: constants (from the config at init) and state. No pointers. */
typedef struct {
  /* constants */
  real_t eta;          /* (m/s)/(rad/s) */
  real_t eps_t;        /* m/s */
  real_t rs0_vy;       /* m/s */
  real_t rs0_r;        /* rad/s */
  real_t drs_vy;       /* m/s */
  real_t drs_r;        /* rad/s */
  real_t tan_beta_max; /* tan(beta_max), - */
  real_t ay_floor;     /* m/s^2 */
  real_t ay_ceiling;   /* m/s^2 */
  real_t ay_margin;    /* - */
  real_t decay;        /* exp(-ts / ay_decay_s), - */
  real_t v_min;        /* m/s */
  real_t r_kin_factor; /* - */
  real_t r_band;       /* rad/s */
  real_t wheelbase_m;  /* L = lf + lr, m */
  real_t lr_m;         /* m */
  real_t unit[RH_REFS_GRID_MAX]; /* grid nodes on [-1, 1] (numpy linspace), - */
  int grid_n;          /* points per axis */
  int max_rounds;      /* radius rounds */
  int newton_iters;    /* polish steps per round */
  /* state (Python get_state: ref.ay_envelope, ref.w_slow, ref.w_slow_started) */
  rh_slow_weights_t weights; /* slow copy, tau = slow_tau_s */
  real_t ay_envelope;  /* |ay| peak-hold envelope, m/s^2 */
  /* counters / diagnostics */
  real_t cost_last;    /* cost of the last search, m/s */
  int rounds_last;     /* radius rounds of the last search */
  int not_converged;   /* searches that ended above eps_t */
} rh_refs_alg1_t;

/* Validate cfg (RH_REFS_E* on error, the struct is then unusable) and set the constants;
 * state reset. p: vehicle (lf, lr used). */
int rh_refs_alg1_init(rh_refs_alg1_t *a, const rh_refs_config_t *cfg, const rh_vehicle_t *p);

/* Forget the envelope, the counters and the slow weight copy (RhonnReferences.reset). */
void rh_refs_alg1_reset(rh_refs_alg1_t *a);

/* out = (wrd rad/s, Vyd m/s, betad rad) for Vx m/s, measured Vy m/s, wr rad/s, road-wheel
 * angle dw rad and measured ay m/s^2 (RhonnReferences.compute; Tt is not used). */
void rh_refs_alg1_compute(rh_refs_alg1_t *a, const rh_rhonn_view_t *m, real_t vx, real_t vy,
                          real_t yaw_rate, real_t delta_w, real_t ay_meas, real_t out[3]);

#endif /* RH_REFS_ALG1_H */
