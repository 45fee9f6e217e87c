/* The nmpc-rhonn reference generator chosen by configuration ([references] kind), wrapped
 * in the sideslip guard when guard_gain_per_s > 0. Python reference:
 * controller/core/references/factory.py (make_rhonn_references).
 *
 *   kind algorithm1: RhonnReferences            (refs_alg1.h)
 *   kind intent:     IntentReferences           (refs_intent.h)
 *   kind blend:      BlendedReferences: IntentReferences + RhonnReferences
 *   kind demand:     BlendedReferences(demand="bicycle"): BicycleDemand + RhonnReferences
 *                    (the default)
 *   kind linear:     not here (init returns RH_REFS_EKIND)
 * Only the parts of the configured kind are initialised and run; the others stay zero. */
#ifndef RH_REFS_H
#define RH_REFS_H

#include "refs_alg1.h"
#include "refs_intent.h"
#include "rh_params.h"
#include "rh_real.h"
#include "rhonn.h"
#include "sideslip_guard.h"
#include "slow_weights.h"

typedef struct {
  int kind;               /* RH_REFS_ALGORITHM1 .. RH_REFS_DEMAND */
  int status;             /* init result (RH_REFS_OK or RH_REFS_E*); compute outputs 0 if not OK */
  real_t v_min;           /* m/s (blend beta and betad denominators) */
  real_t blend_beta_lo;   /* rad */
  real_t blend_span;      /* max(blend_beta_hi - blend_beta_lo, 1e-6), rad */
  real_t weight_last;     /* last blend weight (blend/demand), - */
  rh_refs_alg1_t alg1;    /* algorithm1, blend, demand */
  rh_refs_intent_t intent;/* intent, blend */
  rh_refs_bicycle_t demand;/* demand */
  rh_sideslip_guard_t guard; /* wrapper (enabled when guard_gain_per_s > 0) */
} rh_refs_t;

/* Validate cfg, set the constants of the configured kind, reset. Returns RH_REFS_OK or an
 * RH_REFS_E* code (also kept in r->status). p: vehicle parameters (L, lr, Cf, Cr, m). */
int rh_refs_init(rh_refs_t *r, const rh_refs_config_t *cfg, const rh_vehicle_t *p);

/* Forget envelopes, previous steering angles, counters and slow weight copies (reset()). */
void rh_refs_reset(rh_refs_t *r);

/* Give the slow weight copies the weights W (3, 15) - what SlowWeights.__init__/reset take
 * from model.W; call after init/reset. Only read if the live weights are not finite at the
 * first update (otherwise the copy restarts at the live weights). */
void rh_refs_set_slow_weights(rh_refs_t *r, const real_t W[RH_NW]);

/* out = (yaw_rate_ref rad/s, vy_ref m/s, beta_ref rad) for Vx m/s, Vy m/s, yaw rate rad/s,
 * road-wheel angle dw rad, Tt N m (not used by these designs), measured ay m/s^2. */
void rh_refs_compute(rh_refs_t *r, const rh_rhonn_view_t *model, real_t vx, real_t vy,
                     real_t yaw_rate, real_t delta_w, real_t total_torque, real_t ay_meas,
                     real_t out[3]);

/* sizeof of the structs (binding layout checks), bytes. */
unsigned long rh_refs_sizeof_state(void);
unsigned long rh_refs_sizeof_config(void);

#endif /* RH_REFS_H */
