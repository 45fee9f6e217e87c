/* Slowly updated copy of the RHONN weights the references read (two time scales).
 * Python reference: controller/core/references/slow_weights.py (SlowWeights, collapse).
 *
 *   W_slow <- W_slow + alpha (W - W_slow),  alpha = 1 - exp(-Ts/tau)        (tau = tau_s, s)
 *
 * tau = 0: no copy, the live weights are read. The copy takes the first finite live weights
 * it sees (started = 0 -> 1); non-finite live weights are skipped. */
#ifndef RH_SLOW_WEIGHTS_H
#define RH_SLOW_WEIGHTS_H

#include "rh_real.h"
#include "rhonn.h"

typedef struct {
  real_t copy[RH_NW]; /* W_slow (3, 15) row-major, state units (Python: get_state()[key]) */
  real_t alpha;       /* 1 - exp(-Ts/tau) per update, - (1 when tau = 0) */
  real_t tau_s;       /* time constant, s (0: the live weights are read, no copy) */
  int started;        /* 1 once the copy took live weights (Python: <key>_started) */
} rh_slow_weights_t;

/* tau_s s (negative -> 0), ts s (update period, > 0). The copy starts at zero, not started;
 * rh_slow_weights_set_copy() gives it the model's weights as SlowWeights.__init__ does. */
void rh_slow_weights_init(rh_slow_weights_t *s, double tau_s, double ts);

/* Forget the copy: it restarts at the next finite live weights (SlowWeights.reset without
 * the model: the copy keeps its values until then; see rh_slow_weights_set_copy). */
void rh_slow_weights_reset(rh_slow_weights_t *s);

/* copy := W (what SlowWeights.__init__/reset read from model.W); started unchanged. */
void rh_slow_weights_set_copy(rh_slow_weights_t *s, const real_t W[RH_NW]);

/* One period of the lag with the live weights W (no-op for tau = 0). */
void rh_slow_weights_update(rh_slow_weights_t *s, const real_t W[RH_NW]);

/* The weights the references read: the live W (tau = 0) or the copy. */
const real_t *rh_slow_weights_W(const rh_slow_weights_t *s, const real_t *live);

/* Bilinear (Vy, wr) coefficients C (3, 4) of the read weights at Vx m/s, dw rad
 * (SlowWeights.coefficients; rh_rhonn_bilinear at a = S(Vx), d = S(dw)). */
void rh_slow_weights_coefficients(const rh_slow_weights_t *s, const rh_rhonn_view_t *m,
                                  real_t vx, real_t delta_w, real_t C[12]);

#endif /* RH_SLOW_WEIGHTS_H */
