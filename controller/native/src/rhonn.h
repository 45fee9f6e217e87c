/* RHONN structure (paper eq. 5-8, 17; Python reference: controller/core/model/rhonn.py).
 * States chi = [Vx m/s, Vy m/s, wr rad/s]; xi = [S(Vx), S(Vy), S(wr), S(dw)],
 * S_j(x) = mu_j tanh(beta_j x); phi = the 15 products of distinct subsets of xi in the
 * paper's order (4 singles, 6 pairs, 4 triples, 1 quadruple). W is (3, 15) row-major. */
#ifndef RH_RHONN_H
#define RH_RHONN_H

#include "rh_real.h"

#define RH_NPHI 15
#define RH_NXI 4
#define RH_NW (3 * RH_NPHI)

/* What the reference generators read of the learned model (passed per call, not kept). */
typedef struct {
  const real_t *W;    /* (3, 15) weights, state units */
  real_t mu[RH_NXI];  /* S output scales, - */
  real_t beta[RH_NXI];/* S input gains, 1/unit */
  int increment;      /* 1: chi_{k+1} = chi_k + known + W phi; 0: literal eq. 17 */
} rh_rhonn_view_t;

/* xi_j = mu_j tanh(beta_j x). */
real_t rh_rhonn_xi(const real_t mu[RH_NXI], const real_t beta[RH_NXI], int j, real_t x);

/* phi (15) for xi = (a, b, c, d) in the paper's order. */
void rh_rhonn_phi(real_t a, real_t b, real_t c, real_t d, real_t phi[RH_NPHI]);

/* Coefficients C (3, 4) row-major such that at fixed Vx and dw:
 * W phi = C[:,0] + C[:,1] xi2 + C[:,2] xi3 + C[:,3] xi2 xi3 (xi2 = S(Vy), xi3 = S(wr)).
 * a = xi_0(vx), d = xi_3(dw). */
void rh_rhonn_bilinear(const real_t W[RH_NW], real_t a, real_t d, real_t C[12]);

#endif /* RH_RHONN_H */
