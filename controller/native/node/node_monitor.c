/* Rx monitor (see node_monitor.h; Python reference: can_db/monitor.py RxMonitor). */
#include "node_monitor.h"

#include <math.h>
#include <string.h>

#define RH_MON_TIME_TOL_S 1e-9 /* float rounding of the timeout comparison, s */

void rh_node_monitor_default_config(rh_node_monitor_config_t *cfg) {
  int i;
  for (i = 0; i < RH_MON_STREAMS; ++i) {
    cfg->timeout_s[i] = 3.0 * 0.01; /* RxMonitor timeout_factor x DBC GenMsgCycleTime */
    cfg->window[i] = 1;             /* all monitored messages carry a CRC16 signal */
  }
  cfg->counter_fault_limit = 5;
}

static int monitor_config_ok(const rh_node_monitor_config_t *cfg) {
  int i;
  if (cfg->counter_fault_limit < 1) {
    return 0;
  }
  for (i = 0; i < RH_MON_STREAMS; ++i) {
    if (!(isfinite(cfg->timeout_s[i]) && cfg->timeout_s[i] > 0.0)) {
      return 0;
    }
    if (cfg->window[i] != 0 && cfg->window[i] != 1) {
      return 0;
    }
  }
  return 1;
}

int rh_node_monitor_init(rh_node_monitor_t *m, const rh_node_monitor_config_t *cfg) {
  int ok = cfg != NULL && monitor_config_ok(cfg);
  (void)memset(m, 0, sizeof *m);
  if (ok) {
    m->cfg = *cfg;
  } else {
    rh_node_monitor_default_config(&m->cfg);
  }
  return ok ? 0 : -1;
}

void rh_node_monitor_restart(rh_node_monitor_t *m) {
  /* RxMonitor rebuilt with the old counts: streams and the ignored count start afresh */
  (void)memset(m->streams, 0, sizeof m->streams);
  m->ignored = 0;
}

static void count(rh_node_monitor_t *m, int reason, rh_node_monitor_stream_t *s) {
  m->counts[reason] += 1;
  if (s != NULL) {
    s->rejections[reason] += 1;
  }
}

/* The alive-counter check of both profiles: delta 1 lowers the fault level, any other
 * delta raises it; below the limit a repeated counter is stale, and a jump is accepted
 * (counted) unless the CRC16 window rejects it. RH_MON_ACCEPTED when nothing to count. */
static int check_counter(const rh_node_monitor_t *m, rh_node_monitor_stream_t *s, int window,
                         int counter) {
  int delta, limit = m->cfg.counter_fault_limit;
  int had = s->has_counter, previous = s->last_counter;
  s->has_counter = 1;
  s->last_counter = counter;
  if (!had) {
    return RH_MON_ACCEPTED;
  }
  delta = ((counter - previous) % RH_MON_COUNTER_MODULO + RH_MON_COUNTER_MODULO) %
          RH_MON_COUNTER_MODULO;
  if (delta == 1) {
    if (s->counter_fault_level > 0) {
      s->counter_fault_level -= 1;
    }
    return s->counter_fault_level < limit ? RH_MON_ACCEPTED : RH_MON_COUNTER_FAULT;
  }
  if (s->counter_fault_level < limit) {
    s->counter_fault_level += 1;
  }
  if (s->counter_fault_level >= limit) {
    return RH_MON_COUNTER_FAULT;
  }
  if (delta == 0) {
    return RH_MON_COUNTER_FROZEN;
  }
  if (window && delta > RH_MON_MAX_DELTA_COUNTER) {
    return RH_MON_WRONG_SEQUENCE;
  }
  return RH_MON_COUNTER_JUMP;
}

int rh_node_monitor_process(rh_node_monitor_t *m, int stream, const rh_node_frame_t *f,
                            double now_s) {
  rh_node_monitor_stream_t *s;
  int verdict;
  if (stream < 0 || stream >= RH_MON_STREAMS || f == NULL || f->counter < 0 ||
      f->counter >= RH_MON_COUNTER_MODULO) {
    m->bad_events += 1;
    return RH_MON_BAD_EVENT;
  }
  s = &m->streams[stream];
  s->received += 1;
  verdict = check_counter(m, s, m->cfg.window[stream], f->counter);
  if (verdict != RH_MON_ACCEPTED) {
    count(m, verdict, s);
    if (verdict != RH_MON_COUNTER_JUMP) {
      return verdict;
    }
  }
  s->has_rx = 1;
  s->last_rx_s = now_s;
  s->timed_out_reported = 0;
  s->has_latest = 1;
  s->latest = *f;
  s->accepted += 1;
  return RH_MON_ACCEPTED;
}

void rh_node_monitor_reject(rh_node_monitor_t *m, int reason, int stream) {
  if (reason < 0 || reason >= RH_MON_REASONS || stream < -1 || stream >= RH_MON_STREAMS) {
    m->bad_events += 1;
    return;
  }
  count(m, reason, stream >= 0 ? &m->streams[stream] : NULL);
}

void rh_node_monitor_ignore(rh_node_monitor_t *m) { m->ignored += 1; }

int rh_node_monitor_valid(rh_node_monitor_t *m, int stream, double now_s) {
  rh_node_monitor_stream_t *s;
  if (stream < 0 || stream >= RH_MON_STREAMS) {
    return 0;
  }
  s = &m->streams[stream];
  if (!s->has_rx || s->counter_fault_level >= m->cfg.counter_fault_limit) {
    return 0;
  }
  /* written as "not <=" so a NaN time counts as timed out, never valid */
  if (!(now_s - s->last_rx_s <= m->cfg.timeout_s[stream] + RH_MON_TIME_TOL_S)) {
    if (!s->timed_out_reported) {
      s->timed_out_reported = 1;
      count(m, RH_MON_TIMEOUT, s);
    }
    return 0;
  }
  return 1;
}

const rh_node_frame_t *rh_node_monitor_latest(const rh_node_monitor_t *m, int stream) {
  if (stream < 0 || stream >= RH_MON_STREAMS || !m->streams[stream].has_latest) {
    return NULL;
  }
  return &m->streams[stream].latest;
}
