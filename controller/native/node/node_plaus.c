/* Frozen-signal plausibility (see node_plaus.h; Python: FrozenSignalMonitor). */
#include "node_plaus.h"

#include <math.h>
#include <string.h>

/* Checked signals per stream: the first n physical values of its frame (DBC order). */
static const int checked_signals[RH_MON_STREAMS] = {0, 3, 0, 2, 0};

int rh_node_plaus_checked(int stream) {
  return (stream >= 0 && stream < RH_MON_STREAMS) ? checked_signals[stream] : 0;
}

void rh_node_plaus_default_config(rh_node_plaus_config_t *cfg) {
  cfg->frozen_frames = 10;
  cfg->min_speed_mps = 1.0;
}

int rh_node_plaus_init(rh_node_plaus_t *p, const rh_node_plaus_config_t *cfg) {
  int ok = cfg != NULL && cfg->frozen_frames >= 1 && isfinite(cfg->min_speed_mps) &&
           cfg->min_speed_mps >= 0.0;
  (void)memset(p, 0, sizeof *p);
  if (ok) {
    p->cfg = *cfg;
  } else {
    rh_node_plaus_default_config(&p->cfg);
  }
  return ok ? 0 : -1;
}

void rh_node_plaus_reset(rh_node_plaus_t *p) {
  rh_node_plaus_config_t cfg = p->cfg;
  (void)memset(p, 0, sizeof *p);
  p->cfg = cfg;
}

void rh_node_plaus_update(rh_node_plaus_t *p, int stream, const double *values,
                          double speed_mps) {
  int i, n = rh_node_plaus_checked(stream), faulty = 0;
  int moving = fabs(speed_mps) >= p->cfg.min_speed_mps; /* NaN speed: not moving */
  if (n == 0 || values == NULL) {
    return;
  }
  for (i = 0; i < n; ++i) {
    double v = values[i];
    if (p->has_last[stream][i] && p->last[stream][i] == v && moving) {
      /* held at frozen_frames (no overflow on a stuck sensor); the verdict is the same */
      if (p->repeats[stream][i] < p->cfg.frozen_frames) {
        p->repeats[stream][i] += 1;
      }
    } else {
      p->repeats[stream][i] = 0;
    }
    p->has_last[stream][i] = 1;
    p->last[stream][i] = v;
    if (p->repeats[stream][i] >= p->cfg.frozen_frames - 1) {
      faulty = 1;
    }
  }
  if (faulty && !p->faulty[stream]) {
    p->detections += 1;
  }
  p->faulty[stream] = faulty;
}

int rh_node_plaus_faulty(const rh_node_plaus_t *p, int stream) {
  return (stream >= 0 && stream < RH_MON_STREAMS) ? p->faulty[stream] : 0;
}

int rh_node_plaus_any_faulty(const rh_node_plaus_t *p) {
  int i;
  for (i = 0; i < RH_MON_STREAMS; ++i) {
    if (p->faulty[i]) {
      return 1;
    }
  }
  return 0;
}
