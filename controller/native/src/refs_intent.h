/* Driver-intent and blended references. Python reference:
 * controller/core/references/intent.py (IntentReferences, BicycleDemand, BlendedReferences;
 * the numpy path) and, for BicycleDemand's bicycle steady state,
 * controller/core/references/linear.py (LinearReferences.compute). */
#ifndef RH_REFS_INTENT_H
#define RH_REFS_INTENT_H

#include "refs_alg1.h"
#include "rh_params.h"
#include "rh_real.h"
#include "rhonn.h"
#include "slow_weights.h"

#define RH_REFS_XI_CLIP 0.995 /* |xi/mu| bound before atanh (S^-1), - */

/* IntentReferences: the learned map's linear response to the steering. */
typedef struct {
  /* constants */
  real_t ts;               /* call period, s */
  real_t v_min;            /* m/s */
  real_t intent_lead_s;    /* s */
  real_t intent_ay_margin; /* - (0: no cap) */
  real_t ay_floor;         /* m/s^2 */
  real_t ay_ceiling;       /* m/s^2 */
  real_t r_kin_factor;     /* - */
  real_t r_band;           /* rad/s */
  real_t tan_beta_max;     /* - */
  real_t decay;            /* exp(-ts / ay_decay_s), - */
  real_t wheelbase_m;      /* m */
  real_t lr_m;             /* m */
  /* state (Python get_state: ref.intent.w_slow[_started], ref.intent.ay_envelope,
   * ref.intent.dw_prev) */
  rh_slow_weights_t weights; /* slow copy, tau = slow_tau_s */
  real_t ay_envelope;        /* m/s^2 */
  real_t dw_prev;            /* last dw, rad (NaN: none yet) */
  /* counters / diagnostics */
  real_t gain_last;          /* learned yaw gain wrd/dw of the last call, 1/s */
  int fallbacks;             /* calls with an unstable learned 2x2 matrix (kinematic used) */
} rh_refs_intent_t;

/* BicycleDemand: nominal bicycle steady state + lead + grip cap. */
typedef struct {
  /* constants */
  real_t ts;                  /* s */
  real_t v_min;               /* m/s */
  real_t intent_lead_s;       /* s */
  real_t intent_ay_margin;    /* - (0: no cap) */
  real_t ay_floor;            /* m/s^2 */
  real_t ay_ceiling;          /* m/s^2 */
  real_t decay;               /* exp(-ts / ay_decay_s), - */
  real_t understeer_gradient; /* K = m/L^2 (lr/|Cf| - lf/|Cr|), s^2/m^2 */
  real_t wheelbase_m;         /* L, m */
  real_t lr_m;                /* m */
  real_t beta_k;              /* m lf / (L |Cr|), s^2/m */
  /* state (Python get_state: ref.demand.ay_envelope, ref.demand.dw_prev) */
  real_t ay_envelope;         /* m/s^2 */
  real_t dw_prev;             /* rad (NaN: none yet) */
} rh_refs_bicycle_t;

/* Constants from cfg (validated by rh_refs_alg1_init's rules for ts/ay_decay_s); reset. */
int rh_refs_intent_init(rh_refs_intent_t *s, const rh_refs_config_t *cfg,
                        const rh_vehicle_t *p);
void rh_refs_intent_reset(rh_refs_intent_t *s);
/* (Vyd m/s, wrd rad/s) of the learned linear steady response; 0 if the learned 2x2
 * increment matrix is not a stable equilibrium (IntentReferences.steady_response). */
int rh_refs_intent_steady_response(const rh_refs_intent_t *s, const rh_rhonn_view_t *m,
                                   real_t vx, real_t delta_w, real_t *vy_d, real_t *r_d);
/* out = (wrd rad/s, Vyd m/s, betad rad) (IntentReferences.compute). */
void rh_refs_intent_compute(rh_refs_intent_t *s, const rh_rhonn_view_t *m, real_t vx,
                            real_t delta_w, real_t ay_meas, real_t out[3]);

int rh_refs_bicycle_init(rh_refs_bicycle_t *s, const rh_refs_config_t *cfg,
                         const rh_vehicle_t *p);
void rh_refs_bicycle_reset(rh_refs_bicycle_t *s);
/* out = (wrd rad/s, Vyd m/s, betad rad) (BicycleDemand.compute). */
void rh_refs_bicycle_compute(rh_refs_bicycle_t *s, real_t vx, real_t delta_w, real_t ay_meas,
                             real_t out[3]);

/* Blend weight w = clip((|beta| - beta_lo) / span, 0, 1), - (BlendedReferences), with the
 * measured beta = |Vy| / max(Vx, v_min) (0 if Vx or Vy is not finite); Vx, Vy, v_min m/s,
 * beta_lo rad, span = max(beta_hi - beta_lo, 1e-6) rad. */
real_t rh_refs_blend_weight(real_t vx, real_t vy, real_t v_min, real_t beta_lo, real_t span);

#endif /* RH_REFS_INTENT_H */
