/* RHONN structure: S, phi and the (Vy, wr) bilinear collapse (see rhonn.h). */
#include "rhonn.h"

real_t rh_rhonn_xi(const real_t mu[RH_NXI], const real_t beta[RH_NXI], int j, real_t x) {
  return mu[j] * RH_TANH(beta[j] * x);
}

void rh_rhonn_phi(real_t a, real_t b, real_t c, real_t d, real_t phi[RH_NPHI]) {
  real_t ab = a * b, ac = a * c, ad = a * d, bc = b * c, bd = b * d, cd = c * d;
  real_t abc = ab * c;
  phi[0] = a; phi[1] = b; phi[2] = c; phi[3] = d;
  phi[4] = ab; phi[5] = ac; phi[6] = ad; phi[7] = bc; phi[8] = bd; phi[9] = cd;
  phi[10] = abc; phi[11] = ab * d; phi[12] = ac * d; phi[13] = bc * d; phi[14] = abc * d;
}

/* For each product k: which (Vy, wr) monomial it carries (0: 1, 1: xi2, 2: xi3, 3: xi2 xi3)
 * and which (Vx, dw) factor (0: 1, 1: a, 2: d, 3: a d). Paper order of rhonn.h. */
static const unsigned char MONO[RH_NPHI] = {0, 1, 2, 0, 1, 2, 0, 3, 1, 2, 3, 1, 2, 3, 3};
static const unsigned char TFAC[RH_NPHI] = {1, 0, 0, 2, 1, 1, 3, 0, 2, 2, 1, 3, 3, 2, 3};

void rh_rhonn_bilinear(const real_t W[RH_NW], real_t a, real_t d, real_t C[12]) {
  real_t w4[4][4];
  real_t t[4];
  int i, k, m, f;
  t[0] = RH_R(1.0); t[1] = a; t[2] = d; t[3] = a * d;
  for (i = 0; i < 3; i++) {
    for (m = 0; m < 4; m++)
      for (f = 0; f < 4; f++) w4[m][f] = RH_R(0.0);
    for (k = 0; k < RH_NPHI; k++) w4[MONO[k]][TFAC[k]] = W[i * RH_NPHI + k];
    for (m = 0; m < 4; m++) {
      real_t s = RH_R(0.0);
      for (f = 0; f < 4; f++) s += w4[m][f] * t[f];
      C[i * 4 + m] = s;
    }
  }
}
