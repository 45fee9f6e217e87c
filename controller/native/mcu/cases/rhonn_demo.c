/* Demo case of the MCU harness until the full controller step exists: per step,
 * xi_j = mu_j tanh(beta_j x_j) of the recorded x = [Vx, Vy, wr, dw], phi(xi) (15 outputs) and
 * the bilinear coefficients C of a fixed W (12 outputs): rh_rhonn_xi, rh_rhonn_phi and
 * rh_rhonn_bilinear of src/rhonn.c. Config (MCU_W, MCU_MU, MCU_BETA) generated in Python.
 * Built with the core's C99 flags and -DRH_FLOAT32. */
#include "mcu_case.h"
#include "mcu_case_config.h"
#include "rhonn.h"

typedef char mcu_real_is_float[sizeof(real_t) == sizeof(float) ? 1 : -1];
typedef char mcu_dims_match[(MCU_N_IN == RH_NXI && MCU_N_OUT == RH_NPHI + 12) ? 1 : -1];

void mcu_case_init(void) {}

void mcu_case_step(const float in[MCU_N_IN], float out[MCU_N_OUT]) {
  real_t xi[RH_NXI];
  int j;
  for (j = 0; j < RH_NXI; j++) xi[j] = rh_rhonn_xi(MCU_MU, MCU_BETA, j, in[j]);
  rh_rhonn_phi(xi[0], xi[1], xi[2], xi[3], out);
  rh_rhonn_bilinear(MCU_W, xi[0], xi[3], out + RH_NPHI);
}
