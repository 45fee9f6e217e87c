/* Frozen-signal plausibility: a sensor value that stops changing while the car moves
 * (Python reference: controller/runtime/plausibility.py, FrozenSignalMonitor).
 *
 * A stuck sensor still sends well-formed frames (valid CRC, running alive counter), so E2E
 * protection cannot see it. The same physical value on ``frozen_frames`` consecutive accepted
 * frames at a speed of at least ``min_speed_mps`` makes its message faulty. Checked signals
 * (plausibility.py CHECKED): MOTION_SENSORS YAW_RATE, AX, AY; VEHICLE_EST VX_EST, VY_EST.
 * Wheel speeds are not checked (their noise is below their CAN resolution). */
#ifndef RH_NODE_PLAUS_H
#define RH_NODE_PLAUS_H

#include <stdint.h>

#include "node_monitor.h"

typedef struct {
  int frozen_frames;    /* identical frames that make a signal frozen (>= 1), default 10 */
  double min_speed_mps; /* below this |speed| a repeat is normal, m/s, default 1.0 */
} rh_node_plaus_config_t;

typedef struct {
  rh_node_plaus_config_t cfg;
  int has_last[RH_MON_STREAMS][RH_MON_MAX_SIGNALS];
  double last[RH_MON_STREAMS][RH_MON_MAX_SIGNALS];    /* previous value, signal units */
  int repeats[RH_MON_STREAMS][RH_MON_MAX_SIGNALS];    /* identical consecutive values,
                                                         held at frozen_frames */
  int faulty[RH_MON_STREAMS];                         /* message carries a frozen signal */
  int64_t detections;                                 /* rising edges of a message's fault */
} rh_node_plaus_t;

void rh_node_plaus_default_config(rh_node_plaus_config_t *cfg);
/* 0 on success; -1 for an invalid config (frozen_frames < 1, min speed not finite or < 0):
 * the defaults are used then. */
int rh_node_plaus_init(rh_node_plaus_t *p, const rh_node_plaus_config_t *cfg);
/* Forget every signal (a new plant); the detection count starts at 0 too. */
void rh_node_plaus_reset(rh_node_plaus_t *p);
/* Feed one accepted frame of ``stream`` (physical values), the car's speed ``speed_mps``
 * m/s. Streams without checked signals are ignored. */
void rh_node_plaus_update(rh_node_plaus_t *p, int stream, const double *values,
                          double speed_mps);
/* Checked signals of ``stream`` (its first n values), 0 for an unchecked stream. */
int rh_node_plaus_checked(int stream);
int rh_node_plaus_faulty(const rh_node_plaus_t *p, int stream);
int rh_node_plaus_any_faulty(const rh_node_plaus_t *p);

#endif /* RH_NODE_PLAUS_H */
