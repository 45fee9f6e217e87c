/* Pure-slip Magic Formula (see mf_tyre.h). Operation order follows tyre.py. */
#include "mf_tyre.h"

void rh_mf_curve_init(rh_mf_curve_t *cv, const rh_mf_curve_config_t *cfg) {
  cv->fz0_n = (real_t)cfg->fz0_n;
  cv->c = (real_t)cfg->c;
  cv->d1 = (real_t)cfg->d1;
  cv->d2 = (real_t)cfg->d2;
  cv->k1 = (real_t)cfg->k1;
  cv->k2 = (real_t)cfg->k2;
  cv->k3 = (real_t)cfg->k3;
  cv->e1 = (real_t)cfg->e1;
  cv->e2 = (real_t)cfg->e2;
}

double rh_mf_fz_cap(const rh_mf_curve_config_t *cfg) { return RH_MF_FZ_CAP_FACTOR * cfg->fz0_n; }

real_t rh_mf_force(const rh_mf_curve_t *cv, real_t s, real_t fz_n, real_t mu) {
  real_t fz0 = cv->fz0_n;
  real_t dfz = (fz_n - fz0) / fz0;                                /* - */
  real_t K = fz_n * (cv->k1 + cv->k2 * dfz) * RH_EXP(cv->k3 * dfz); /* N/rad */
  real_t D = mu * fz_n * (cv->d1 + cv->d2 * dfz);                  /* N */
  real_t E = RH_FMIN(cv->e1 + cv->e2 * dfz, RH_R(1.0));            /* - */
  real_t C = cv->c, u;
  if (D <= RH_R(1e-9) || K <= RH_R(0.0)) return RH_R(0.0);
  u = (K / (C * D)) * s;
  return D * RH_SIN(C * RH_ATAN(u - E * (u - RH_ATAN(u))));
}

void rh_mf_eval(const rh_mf_curve_t *cv, real_t s, real_t fz_n, real_t mu, real_t out[3]) {
  real_t fz0 = cv->fz0_n;
  real_t dfz = (fz_n - fz0) / fz0;
  real_t ex = RH_EXP(cv->k3 * dfz);
  real_t kpoly = cv->k1 + cv->k2 * dfz;
  real_t K = fz_n * kpoly * ex;                                      /* N/rad */
  real_t dK = ex * (kpoly + fz_n * (cv->k2 + kpoly * cv->k3) / fz0); /* (N/rad)/N */
  real_t dpoly = cv->d1 + cv->d2 * dfz;
  real_t D = mu * fz_n * dpoly;                                      /* N */
  real_t dD = mu * (dpoly + fz_n * cv->d2 / fz0);                    /* N/N */
  real_t E = cv->e1 + cv->e2 * dfz;
  real_t dE = cv->e2 / fz0; /* 1/N */
  real_t C = cv->c, B, dB, u, atu, phi, y, sy, g, dphi_du;
  if (E > RH_R(1.0)) { /* MF requires E <= 1 (else the curve folds back) */
    E = RH_R(1.0);
    dE = RH_R(0.0);
  }
  if (D <= RH_R(1e-9) || K <= RH_R(0.0)) {
    out[0] = RH_R(0.0); out[1] = RH_R(0.0); out[2] = RH_R(0.0);
    return;
  }
  B = K / (C * D);                          /* 1/rad */
  dB = (dK * D - K * dD) / (C * D * D);     /* 1/(rad N) */
  u = B * s;
  atu = RH_ATAN(u);
  phi = u - E * (u - atu);
  y = C * RH_ATAN(phi);
  sy = RH_SIN(y);
  g = D * RH_COS(y) * C / (RH_R(1.0) + phi * phi); /* dF/dphi, N */
  dphi_du = (RH_R(1.0) - E) + E / (RH_R(1.0) + u * u);
  out[0] = D * sy;
  out[1] = g * dphi_du * B;
  out[2] = dD * sy + g * (dphi_du * s * dB - (u - atu) * dE);
}
