/* The controller node's per-cycle logic: received frames -> controller step -> frames to send
 * (Python reference: controller/runtime/node.py, ControllerNode, without sockets, clocks
 * or frame encoding; the frame layer decodes and encodes around it).
 *
 * Every communication cycle (10 ms) the node answers with the physical values of
 * WHEEL_TORQUE_CMD, CTRL_STATUS and CTRL_REFS (rh_node_tx_t). The full controller step
 * (rh_ctrl_step) runs every ``mpc_every`` answers; in between the held Delta M is
 * re-allocated with the fresh pedal torque (rh_ctrl_allocate_only). Modes (CTRL_STATUS.MODE):
 *
 * * STAB_ENABLE = 0 -> STANDBY: Delta M = 0;
 * * a sensor stream (MOTION_SENSORS, WHEEL_SPEEDS, VEHICLE_EST) invalid, timed out or frozen
 *   -> DEGRADED_SENSORS: Delta M = 0, the driver's torque passed through, learning frozen;
 * * driver stream invalid or timed out -> DRIVER_LOST_RAMPDOWN: every wheel torque ramps to
 *   zero (INIT stays INIT until the driver frame first arrives);
 * * the core failed -> FAULT, latched (node_fault.h).
 * The output envelope (node_envelope.h) guards every answer.
 *
 * Lockstep (sync-driven): non-SYNC frames go to rh_node_logic_rx (buffered per stream, at most
 * burst_bound frames, the oldest dropped and counted), the SYNC (or a frame with the SYNC's
 * ID the decoder rejected) to rh_node_logic_sync, which validates the burst at the SYNC's
 * simulated time and answers. Free-running: rh_node_logic_accept on arrival at the caller's
 * monotonic time, rh_node_logic_tick on the node's own schedule.
 *
 * Decoded values and times are double (SIM_TIME needs it); the node computes in double in
 * both builds and converts to real_t only at the core's boundary (rh_inputs_t), as the
 * Python binding does. */
#ifndef RH_NODE_LOGIC_H
#define RH_NODE_LOGIC_H

#include <stdint.h>

#include "node_envelope.h"
#include "node_fault.h"
#include "node_monitor.h"
#include "node_plaus.h"
#include "rhonn_core.h"

/* CTRL_STATUS.MODE (node.py Mode). */
#define RH_NODE_MODE_INIT 0
#define RH_NODE_MODE_ACTIVE 1
#define RH_NODE_MODE_STANDBY 2
#define RH_NODE_MODE_DEGRADED_SENSORS 3
#define RH_NODE_MODE_DRIVER_LOST_RAMPDOWN 4
#define RH_NODE_MODE_FAULT 5

/* CTRL_STATUS.FAULT_BITS bit positions (node.py Fault). */
#define RH_NODE_BIT_SENSORS_INVALID 0
#define RH_NODE_BIT_DRIVER_INVALID 1
#define RH_NODE_BIT_SYNC_LOST 2
#define RH_NODE_BIT_SOLVER_FALLBACK 3
#define RH_NODE_BIT_NONFINITE_INPUT 4 /* defined by the DBC; node.py never sets it */
#define RH_NODE_BIT_LEARNING_RESET 5  /* defined by the DBC; node.py never sets it */
#define RH_NODE_BIT_TORQUE_CLIPPED 6
#define RH_NODE_BIT_RX_OVERLOAD 7

#define RH_NODE_DATA_STREAMS 4 /* the monitored streams but SYNC (RH_MON_DRIVER..VEHICLE_EST) */
#define RH_NODE_BURST_MAX 6    /* largest burst_bound, frames per stream */

/* What the frame layer saw in one received frame. */
#define RH_NODE_RX_DECODED 0  /* a well-formed frame of a monitored stream */
#define RH_NODE_RX_REJECTED 1 /* the decoder rejected it (reason RH_MON_UNKNOWN_ID..OUT_OF_RANGE) */
#define RH_NODE_RX_IGNORED 2  /* a well-formed frame of a message the node does not monitor */

typedef struct {
  int kind;              /* RH_NODE_RX_* */
  int stream;            /* RH_MON_* stream of the frame's ID, -1 when none (unknown ID or a
                            message not monitored) */
  int reason;            /* RH_NODE_RX_REJECTED: the decoder's RH_MON_* reason */
  rh_node_frame_t frame; /* RH_NODE_RX_DECODED: alive counter and physical values */
} rh_node_rx_t;

typedef struct {
  double comm_period_s;            /* communication cycle, s (> 0), default 0.01 */
  int mpc_every;                   /* answers per full step: max(1, round(Ts / comm)), >= 1 */
  int controller_id;               /* CTRL_STATUS.CONTROLLER_ID 0..15 (node.py CONTROLLER_IDS) */
  double peak_torque_nm;           /* per motor, N m (> 0) */
  double peak_power_w;             /* per motor, W (> 0) */
  double plant_restart_backstep_s; /* SYNC time back by more than this: a new plant, s */
  int burst_bound[RH_NODE_DATA_STREAMS]; /* lockstep buffer per stream, 1..RH_NODE_BURST_MAX */
  rh_node_monitor_config_t monitor;
  rh_node_plaus_config_t plaus;
  rh_node_envelope_config_t envelope;
  rh_node_fault_config_t fault;
} rh_node_logic_config_t;

/* The node's view of the bus for the core (Python: ControllerInputs), double. */
typedef struct {
  double swa_rad;         /* steering-wheel angle, rad */
  double accel_pedal;     /* 0..1 */
  double brake_pedal;     /* 0..1 */
  double yaw_rate;        /* rad/s */
  double ax, ay;          /* m/s^2 */
  double wheel_speeds[4]; /* rad/s */
  double vx, vy;          /* m/s */
  int stab_enable;        /* the stability function is enabled */
  int sensors_valid;      /* every sensor stream valid, fresh and not frozen */
} rh_node_inputs_t;

/* Physical values of the three frames of one answer (the frame layer encodes them). */
typedef struct {
  double tq_nm[4];           /* WHEEL_TORQUE_CMD TQ_FL, TQ_FR, TQ_RL, TQ_RR, N m */
  int echo_cycle;            /* ECHO_CYCLE of all three: SYNC CYCLE mod 256 (0 before one) */
  int mode;                  /* CTRL_STATUS.MODE, RH_NODE_MODE_* */
  int fault_bits;            /* CTRL_STATUS.FAULT_BITS, bits RH_NODE_BIT_* */
  int qp_status;             /* CTRL_STATUS.QP_STATUS, RH_QP_* */
  int qp_iter;               /* CTRL_STATUS.QP_ITER (the encoder saturates it) */
  double compute_time_us;    /* CTRL_STATUS.COMPUTE_TIME, us: 0 here (the node reads no
                                clock); the integrator may write its measurement */
  int controller_id;         /* CTRL_STATUS.CONTROLLER_ID */
  double delta_m_nm;         /* CTRL_REFS.DELTA_M of the torques sent, N m */
  double yaw_rate_ref_deg_s; /* CTRL_REFS.YAW_RATE_REF, deg/s */
  double beta_ref_deg;       /* CTRL_REFS.BETA_REF, deg */
  int64_t cycle;             /* SYNC CYCLE answered (-1 before the first SYNC) */
  double sim_time_s;         /* its SIM_TIME, s (0 before the first SYNC) */
  int mpc_update;            /* this answer ran the full step */
} rh_node_tx_t;

typedef struct {
  rh_node_logic_config_t cfg;
  rh_node_monitor_t monitor;
  rh_node_plaus_t plaus;
  rh_node_envelope_t envelope;
  rh_node_fault_t fault;
  rh_node_inputs_t inputs;  /* persistent: a stream not yet seen keeps its defaults */
  rh_node_outputs_t out;    /* the controller's outputs of the last answer (record.outputs) */
  double torques[4];        /* wheel torques of the last answer, N m */
  double env_prev[4];       /* the envelope's previous output, N m */
  int mode;                 /* RH_NODE_MODE_* of the last answer */
  int64_t mode_changes;
  int cycles_since_mpc;
  int64_t plant_restarts;
  int has_sync;
  rh_node_frame_t last_sync; /* last accepted SYNC (values: CYCLE, SIM_TIME s) */
  double last_stamp_s;       /* SIM_TIME of the last SYNC, s (stamps early rejections) */
  rh_node_frame_t burst[RH_NODE_DATA_STREAMS][RH_NODE_BURST_MAX]; /* oldest first */
  int burst_n[RH_NODE_DATA_STREAMS];
  int64_t burst_drops;       /* rx drops "burst_full" */
  int64_t secoc_evicted;     /* rx drops "secoc_pending_full" (the SecOC layer's total) */
  int64_t drops_answered;    /* rx drops already reported by an answer */
  int64_t rx_overload_cycles;
  int64_t bad_events;        /* events the node could not place (wrong kind/stream) */
  rh_node_tx_t last_tx;      /* the last answer */
} rh_node_logic_t;

/* Defaults: 10 ms cycle, mpc_every 5 (Ts 50 ms), controller_id 15 (unknown), motors 450 N m
 * and 45 kW (controller/config/vehicle.toml [motors]), back-step 0.5 s, burst 3 frames per
 * stream (3 cycles of 10 ms messages), and each module's defaults. */
void rh_node_logic_default_config(rh_node_logic_config_t *cfg);
/* 0 on success; -1 when the config (or a module's) is invalid: the node is then set up with
 * FAULT latched (no core step; the driver's torque or 0 N m, enveloped). */
int rh_node_logic_init(rh_node_logic_t *st, const rh_node_logic_config_t *cfg);

/* Lockstep: one received frame that is not the SYNC. A decoded frame of a monitored data
 * stream is buffered until the SYNC; a rejected or ignored frame is counted now. Returns 0,
 * or -1 for an event the node cannot place (a SYNC, a bad kind or stream; counted). */
int rh_node_logic_rx(rh_node_logic_t *st, const rh_node_rx_t *ev);
/* Lockstep: the SYNC frame (decoded, or rejected by the decoder: stream RH_MON_SYNC).
 * Validates the buffered burst, then the ``n_released`` frames in ``released`` (SecOC: the
 * burst's frames whose authenticators verified; NULL/0 without SecOC), then the SYNC, at
 * the SYNC's simulated time, and answers into *tx. Returns 1 when answered, 0 when not (a
 * rejected SYNC: the plant's timeout handles it), -1 for a bad event (counted). ``ctrl``:
 * the initialised core (NULL: the core could not be initialised -> FAULT). */
int rh_node_logic_sync(rh_node_logic_t *st, rh_ctrl_t *ctrl, const rh_node_rx_t *sync,
                       const rh_node_rx_t *released, int n_released, rh_node_tx_t *tx);
/* rh_node_logic_sync in two halves, for a layer that keeps the released frames in buffers
 * of its own (the PIL firmware's SecOC): _sync_begin validates the event, handles a plant
 * restart, stamps the cycle (last_stamp_s) and validates the buffered burst (0, or -1 for a
 * bad event, counted: nothing else happens then); the layer gives each released frame to
 * rh_node_logic_accept at last_stamp_s; _sync_end validates the SYNC and answers (1 when
 * answered, 0 for a rejected SYNC). rh_node_logic_sync is exactly these three steps. */
int rh_node_logic_sync_begin(rh_node_logic_t *st, rh_ctrl_t *ctrl, const rh_node_rx_t *sync);
int rh_node_logic_sync_end(rh_node_logic_t *st, rh_ctrl_t *ctrl, const rh_node_rx_t *sync,
                           rh_node_tx_t *tx);
/* Free-running: validate one frame on arrival at ``now_s`` (monotonic s). 0, or -1 for a bad
 * event (counted). */
int rh_node_logic_accept(rh_node_logic_t *st, const rh_node_rx_t *ev, double now_s);
/* Free-running: answer one cycle at ``now_s`` (monotonic s) into *tx. */
void rh_node_logic_tick(rh_node_logic_t *st, rh_ctrl_t *ctrl, double now_s, rh_node_tx_t *tx);
/* The per-cycle step both modes share (node.py _answer): validity at ``now_s`` s, the core's
 * inputs, the core step (or its skip per the fault state), fault reaction, envelope, and
 * the frames' physical values into *tx. */
void rh_node_logic_answer(rh_node_logic_t *st, rh_ctrl_t *ctrl, double now_s,
                          rh_node_tx_t *tx);
/* The SecOC layer's running total of unverified frames it evicted (its bounded queue):
 * a change sets RX_OVERLOAD in the next answer. */
void rh_node_logic_set_secoc_evicted(rh_node_logic_t *st, int64_t total);
/* sizeof rh_node_logic_t, rh_node_logic_config_t, rh_node_tx_t, rh_node_rx_t, bytes
 * (layout checks of bindings). */
void rh_node_logic_sizes(int64_t out[4]);

#endif /* RH_NODE_LOGIC_H */
