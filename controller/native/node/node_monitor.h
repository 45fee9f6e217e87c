/* Receiver-side supervision of the node's monitored message streams (Python reference:
 * can_db/monitor.py, RxMonitor): per stream a timeout, the alive-counter check of the CRC8 and
 * CRC16 E2E profiles with a fault level, a validity flag, the latest accepted frame and
 * counts of every rejection by reason. Time is passed in by the caller (simulated or
 * monotonic seconds, double); the monitor never reads a clock.
 *
 * Input events come from the frame layer's decoder: a decoded frame of a monitored stream
 * (rh_node_monitor_process), a frame the decoder rejected (rh_node_monitor_reject) or a
 * well-formed frame of a message the node does not monitor (rh_node_monitor_ignore). */
#ifndef RH_NODE_MONITOR_H
#define RH_NODE_MONITOR_H

#include <stdint.h>

/* Monitored streams (node.py MONITORED, in its order). */
#define RH_MON_DRIVER 0      /* DRIVER_INPUTS: SWA deg, ACCEL_PEDAL %, BRAKE_PEDAL %, STAB_ENABLE */
#define RH_MON_MOTION 1      /* MOTION_SENSORS: YAW_RATE deg/s, AX m/s^2, AY m/s^2 */
#define RH_MON_WHEELS 2      /* WHEEL_SPEEDS: WS_FL, WS_FR, WS_RL, WS_RR rad/s */
#define RH_MON_VEHICLE_EST 3 /* VEHICLE_EST: VX_EST m/s, VY_EST m/s */
#define RH_MON_SYNC 4        /* SYNC: CYCLE -, SIM_TIME s */
#define RH_MON_STREAMS 5
#define RH_MON_MAX_SIGNALS 4 /* physical values per frame, in the DBC's signal order */

/* Rejection reasons (can_db/codec.py Rejection, in its order). 0..4 come from the decoder,
 * 5..8 from the counter check, 9 from the timeout. */
#define RH_MON_UNKNOWN_ID 0
#define RH_MON_NOT_DATA_FRAME 1
#define RH_MON_WRONG_LENGTH 2
#define RH_MON_BAD_CRC 3
#define RH_MON_OUT_OF_RANGE 4
#define RH_MON_COUNTER_FROZEN 5
#define RH_MON_COUNTER_JUMP 6  /* counted, the frame accepted while the level is below the limit */
#define RH_MON_COUNTER_FAULT 7
#define RH_MON_WRONG_SEQUENCE 8
#define RH_MON_TIMEOUT 9
#define RH_MON_REASONS 10

/* Results of rh_node_monitor_process besides a rejection reason (>= 0). */
#define RH_MON_ACCEPTED (-1)
#define RH_MON_BAD_EVENT (-2)  /* stream, reason or counter out of range: counted, ignored */

#define RH_MON_COUNTER_MODULO 16
#define RH_MON_MAX_DELTA_COUNTER 3 /* CRC16 profile: largest counter delta accepted */

typedef struct {
  double timeout_s[RH_MON_STREAMS]; /* no accepted frame for longer: invalid, s (> 0) */
  int window[RH_MON_STREAMS];       /* 1: CRC16 profile (counter-delta window), 0: CRC8 */
  int counter_fault_limit;          /* fault level at which a stream is invalid (>= 1) */
} rh_node_monitor_config_t;

/* One decoded frame: alive counter 0..15 and physical values (units per stream above). */
typedef struct {
  int counter;
  double values[RH_MON_MAX_SIGNALS];
} rh_node_frame_t;

typedef struct {
  int has_rx;                 /* a frame was accepted since the start */
  double last_rx_s;           /* time of the last accepted frame, s */
  int has_counter;            /* a counter was seen (accepted or not) */
  int last_counter;           /* last received alive counter */
  int counter_fault_level;    /* 0..counter_fault_limit */
  int timed_out_reported;     /* the current timeout has been counted */
  int has_latest;
  rh_node_frame_t latest;     /* most recent accepted frame (may be stale) */
  int64_t received, accepted; /* decoded frames seen / accepted */
  int64_t rejections[RH_MON_REASONS];
} rh_node_monitor_stream_t;

typedef struct {
  rh_node_monitor_config_t cfg;
  rh_node_monitor_stream_t streams[RH_MON_STREAMS];
  int64_t counts[RH_MON_REASONS]; /* every rejection by reason (kept over restarts) */
  int64_t ignored;                /* well-formed frames of messages not monitored */
  int64_t bad_events;             /* events with an out-of-range stream, reason or counter */
} rh_node_monitor_t;

/* The DBC's defaults: timeout 3 x GenMsgCycleTime (10 ms for all five streams, rhonn_tv.dbc),
 * CRC16 profile on all five, counter fault limit 5 (RxMonitor's defaults). */
void rh_node_monitor_default_config(rh_node_monitor_config_t *cfg);
/* 0 on success, -1 for an invalid config (timeouts not finite and > 0, window not 0/1,
 * limit < 1): the monitor is then initialised with the defaults. */
int rh_node_monitor_init(rh_node_monitor_t *m, const rh_node_monitor_config_t *cfg);
/* A new plant: every stream forgets its state; the counts by reason are kept. */
void rh_node_monitor_restart(rh_node_monitor_t *m);
/* Validate one decoded frame of ``stream`` at ``now_s`` s: RH_MON_ACCEPTED (a counter jump
 * is counted and accepted), the rejection reason, or RH_MON_BAD_EVENT. */
int rh_node_monitor_process(rh_node_monitor_t *m, int stream, const rh_node_frame_t *f,
                            double now_s);
/* Count a decoder rejection (reason 0..4, or any reason) of ``stream`` (-1: no monitored
 * stream, e.g. an unknown ID). */
void rh_node_monitor_reject(rh_node_monitor_t *m, int reason, int stream);
/* Count a well-formed frame of a message this node does not monitor. */
void rh_node_monitor_ignore(rh_node_monitor_t *m);
/* 1 when ``stream`` has a fresh accepted frame and a healthy counter at ``now_s`` s; the
 * first check after a timeout counts it (RH_MON_TIMEOUT). A NaN time is never valid. */
int rh_node_monitor_valid(rh_node_monitor_t *m, int stream, double now_s);
/* Most recent accepted frame of ``stream`` (NULL when none or a bad stream). */
const rh_node_frame_t *rh_node_monitor_latest(const rh_node_monitor_t *m, int stream);

#endif /* RH_NODE_MONITOR_H */
