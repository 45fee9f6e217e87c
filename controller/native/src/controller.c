/* The controller step over the modules (Python reference: controller/core/mpc/controller.py
 * MpcController.step / allocate_only, controller/core/passive.py). See rhonn_core.h. */
#include <math.h>
#include <string.h>

#include "passive.h"
#include "pedal_map.h"
#include "rhonn_core.h"

static void rollout_rhonn(const void *model, const real_t x0[RH_NX], const real_t *ubar, int n,
                          const rh_ctx_t *ctx, real_t *xbar, real_t *A, real_t *B) {
  rh_rhonn_model_rollout((const rh_rhonn_model_t *)model, x0, ubar, n, ctx, xbar, A, B);
}

/* One pass per stage: x_{i+1}, A_i, B_i at (x_i, u_i) (the physics baselines). */
typedef void (*stage_fn)(const void *model, const real_t x[3], real_t dm, const rh_ctx_t *ctx,
                         real_t xn[3], real_t A[9], real_t B[3]);

static void rollout_stages(stage_fn stage, const void *model, const real_t x0[RH_NX],
                           const real_t *ubar, int n, const rh_ctx_t *ctx, real_t *xbar,
                           real_t *A, real_t *B) {
  int i;
  xbar[0] = x0[0]; xbar[1] = x0[1]; xbar[2] = x0[2];
  for (i = 0; i < n; i++)
    stage(model, xbar + 3 * i, ubar[i], ctx, xbar + 3 * (i + 1), A + 9 * i, B + 3 * i);
}

static void stage_mf(const void *m, const real_t x[3], real_t dm, const rh_ctx_t *ctx,
                     real_t xn[3], real_t A[9], real_t B[3]) {
  rh_seven_dof_predict_linearize((const rh_seven_dof_t *)m, x, dm, ctx, xn, A, B);
}

static void stage_lmpc(const void *m, const real_t x[3], real_t dm, const rh_ctx_t *ctx,
                       real_t xn[3], real_t A[9], real_t B[3]) {
  rh_bicycle_predict_linearize((const rh_bicycle_t *)m, x, dm, ctx, xn, A, B);
}

static void rollout_mf(const void *model, const real_t x0[RH_NX], const real_t *ubar, int n,
                       const rh_ctx_t *ctx, real_t *xbar, real_t *A, real_t *B) {
  rollout_stages(stage_mf, model, x0, ubar, n, ctx, xbar, A, B);
}

static void rollout_lmpc(const void *model, const real_t x0[RH_NX], const real_t *ubar, int n,
                         const rh_ctx_t *ctx, real_t *xbar, real_t *A, real_t *B) {
  rollout_stages(stage_lmpc, model, x0, ubar, n, ctx, xbar, A, B);
}

int rh_ctrl_init(rh_ctrl_t *c, const rh_ctrl_config_t *cfg) {
  int rc;
  (void)memset(c, 0, sizeof *c);
  if (!(cfg->ts_s > 0.0) || cfg->kind < RH_CTRL_NMPC_RHONN || cfg->kind > RH_CTRL_PASSIVE)
    return -1;
  c->kind = cfg->kind;
  c->grip_demand = cfg->grip_demand;
  c->envelope = cfg->envelope;
  c->env_v_min = cfg->handling.v_min_mps;
  c->env_yaw_margin = cfg->handling.yaw_margin;
  c->env_rear_slip_factor = cfg->handling.rear_slip_factor;
  c->fixed_point_share = cfg->handling.fixed_point_share > 0.0;
  c->peak_torque = (real_t)cfg->vehicle.peak_torque_nm;
  c->steering_ratio = (real_t)cfg->vehicle.steering_ratio;
  c->v_min = (real_t)cfg->v_min_mps;
  c->dm_cap = (real_t)cfg->qp.delta_m_max_nm;
  rh_alloc_init(&c->alloc, &cfg->vehicle, &cfg->alloc);
  /* the car without a controller: the driver's torque straight to the motors (no slew) */
  if (cfg->kind == RH_CTRL_PASSIVE) c->alloc.rate_step = RH_R(0.0);
  if (cfg->kind != RH_CTRL_PASSIVE) {
    rc = rh_qp_init(&c->qp, &cfg->qp, cfg->ts_s);
    if (rc != 0) return rc;
  }
  if (cfg->kind == RH_CTRL_NMPC_RHONN) {
    real_t w0[RH_NW];
    int k;
    for (k = 0; k < RH_NW; k++) w0[k] = (real_t)cfg->rhonn_w0[k];
    if (rh_rhonn_model_init(&c->u.rhonn.model, &cfg->rhonn, &cfg->vehicle, cfg->ts_s, w0) != 0 ||
        rh_rhonn_model_init_dm_gain(&c->u.rhonn.model, &cfg->rhonn_dm_gain) != 0)
      return -1;
    c->u.rhonn.use_linear = cfg->refs.kind == RH_REFS_LINEAR;
    if (c->u.rhonn.use_linear)
      rh_linear_refs_init(&c->u.rhonn.linear, &cfg->vehicle);
    else if (rh_refs_init(&c->u.rhonn.refs, &cfg->refs, &cfg->vehicle) != RH_REFS_OK)
      return -1;
    c->qp.has_b_prev = 1;
    rh_rhonn_model_b_prev(&c->u.rhonn.model, c->qp.b_prev);
  } else if (cfg->kind == RH_CTRL_NMPC_MF) {
    rh_seven_dof_init(&c->u.mf.model, &cfg->vehicle, &cfg->seven_dof);
    rh_linear_refs_init(&c->u.mf.refs, &cfg->vehicle);
  } else if (cfg->kind == RH_CTRL_LMPC) {
    rh_bicycle_init(&c->u.lmpc.model, &cfg->vehicle, cfg->bicycle_h_max_s);
    rh_linear_refs_init(&c->u.lmpc.refs, &cfg->vehicle);
  }
  rh_grip_init(&c->grip, &cfg->grip, &cfg->vehicle, cfg->ts_s);
  if (cfg->grip_demand)
    rh_grip_demand_init(&c->gdemand, &cfg->handling, &cfg->vehicle, cfg->refs.v_min);
  {
    const rh_vehicle_t *p = &cfg->vehicle;
    double L = p->lf_m + p->lr_m;
    c->slip_per_mu = 3.0 * p->mass_kg * RH_GRIP_G * p->lf_m / (L * fabs(p->cr_axle_n_per_rad));
  }
  c->ctx.ts = (real_t)cfg->ts_s;
  c->confidence = RH_R(1.0);
  rh_ctrl_reset(c);
  return 0;
}

void rh_ctrl_reset(rh_ctrl_t *c) {
  rh_outputs_t *o = &c->out;
  int i;
  if (c->kind == RH_CTRL_NMPC_RHONN) {
    rh_rhonn_model_reset(&c->u.rhonn.model);
    if (c->u.rhonn.use_linear) {
      rh_linear_refs_reset(&c->u.rhonn.linear);
    } else {
      rh_refs_reset(&c->u.rhonn.refs);
      rh_refs_set_slow_weights(&c->u.rhonn.refs, rh_rhonn_model_weights(&c->u.rhonn.model));
    }
  } else if (c->kind == RH_CTRL_NMPC_MF) {
    rh_linear_refs_reset(&c->u.mf.refs);
  } else if (c->kind == RH_CTRL_LMPC) {
    rh_linear_refs_reset(&c->u.lmpc.refs);
  }
  if (c->kind != RH_CTRL_PASSIVE) rh_qp_reset(&c->qp);
  rh_alloc_reset(&c->alloc);
  rh_grip_reset(&c->grip);
  if (c->grip_demand) rh_grip_demand_reset(&c->gdemand);
  for (i = 0; i < 4; i++) o->torques[i] = RH_R(0.0);
  o->total_torque = RH_R(0.0); o->delta_m = RH_R(0.0);
  o->yaw_rate_ref = RH_R(0.0); o->vy_ref = RH_R(0.0); o->beta_ref = RH_R(0.0);
  o->qp_status = RH_QP_NOT_RUN;
  o->qp_iterations = 0;
  o->fallback = 0;
  for (i = 0; i < 3; i++) o->model_prediction[i] = (real_t)NAN;
  c->dm_held = RH_R(0.0); c->dm_prev = RH_R(0.0);
  c->steps = 0; c->invalid_steps = 0;
}

/* Every numeric input finite (one sum, as MpcController.inputs_finite). */
static int inputs_finite(const rh_inputs_t *in) {
  real_t s = in->swa_rad + in->accel_pedal + in->brake_pedal + in->yaw_rate + in->ax + in->ay +
             in->vx + in->vy;
  if (!in->wheel_speeds_usable) return 0;
  s = s + (in->wheel_speeds[0] + in->wheel_speeds[1] + in->wheel_speeds[2] +
           in->wheel_speeds[3]);
  return RH_FINITE(s);
}

static void copy_wheel_speeds(rh_ctrl_t *c, const rh_inputs_t *in) {
  int i;
  for (i = 0; i < 4; i++)
    c->ctx.wheel_speeds[i] = in->wheel_speeds_usable ? in->wheel_speeds[i] : RH_R(0.0);
}

static void allocate(rh_ctrl_t *c, const rh_inputs_t *in, real_t tt, real_t dm, int limits_current) {
  rh_outputs_t *o = &c->out;
  rh_alloc_allocate(&c->alloc, tt, dm, in->ax, in->ay, c->ctx.wheel_speeds, limits_current,
                    o->torques);
  o->total_torque = tt;
  o->delta_m = c->alloc.dm_applied;
  c->dm_prev = c->alloc.dm_applied;
}

static void passive_step(rh_ctrl_t *c, const rh_inputs_t *in) {
  rh_passive_out_t po;
  rh_outputs_t *o = &c->out;
  int i;
  rh_passive_step(&c->alloc, in->accel_pedal, in->brake_pedal, in->ax, in->ay,
                  in->wheel_speeds_usable ? in->wheel_speeds : NULL, &po);
  for (i = 0; i < 4; i++) o->torques[i] = po.torques[i];
  o->total_torque = po.total_torque;
  o->delta_m = po.delta_m;
  o->qp_status = RH_QP_NOT_RUN;
  o->qp_iterations = 0;
  o->fallback = 0;
}

void rh_ctrl_step(rh_ctrl_t *c, const rh_inputs_t *in, rh_outputs_t *out) {
  rh_outputs_t *o = &c->out;
  int finite, valid, active, kind = c->kind;
  real_t tt, dw;
  if (kind == RH_CTRL_PASSIVE) {
    passive_step(c, in);
    *out = *o;
    return;
  }
  c->steps += 1;
  finite = inputs_finite(in);
  valid = in->sensors_valid && finite;
  if (!valid) c->invalid_steps += 1;
  copy_wheel_speeds(c, in);
  tt = rh_pedal_total_torque(in->accel_pedal, in->brake_pedal, c->peak_torque);
  dw = RH_FINITE(in->swa_rad) ? in->swa_rad / c->steering_ratio : RH_R(0.0);
  c->ctx.delta_w = dw;
  c->ctx.total_torque = tt;
  c->ctx.delta_m_prev = c->dm_prev;
  if (valid) {
    c->x[0] = in->vx;
    c->x[1] = in->vy;
    c->x[2] = in->yaw_rate;
    if (!RH_FINITE(c->x[0] + c->x[1] + c->x[2])) valid = 0;
  }
  if (kind == RH_CTRL_NMPC_RHONN) {
    (void)rh_rhonn_model_observe(&c->u.rhonn.model, c->x, valid);
    /* the learned Delta M effectiveness moves d x_{k+1} / d Delta M_{k-1} (after a learning
     * step, a reset or a restore alike) */
    if (c->u.rhonn.model.dm_gain_on) rh_rhonn_model_b_prev(&c->u.rhonn.model, c->qp.b_prev);
  }
  if (valid && (c->grip_demand || c->envelope))
    rh_grip_update(&c->grip, (double)in->vx, (double)in->vy, (double)in->yaw_rate, (double)dw,
                   (double)in->ax, (double)in->ay);
  if (valid) {
    real_t r[3];
    if (c->grip_demand && kind == RH_CTRL_NMPC_RHONN) {
      rh_rhonn_view_t v = rh_rhonn_model_view(&c->u.rhonn.model);
      rh_grip_demand_compute(&c->gdemand, c->grip.mu,
                             c->fixed_point_share ? &c->u.rhonn.refs : NULL,
                             &v, in->vx, in->vy, in->yaw_rate, dw, tt, in->ay, r);
    } else if (c->grip_demand) {
      rh_grip_demand_compute(&c->gdemand, c->grip.mu, NULL, NULL, in->vx, in->vy,
                             in->yaw_rate, dw, tt, in->ay, r);
    } else if (kind == RH_CTRL_NMPC_RHONN && !c->u.rhonn.use_linear) {
      rh_rhonn_view_t v = rh_rhonn_model_view(&c->u.rhonn.model);
      rh_refs_compute(&c->u.rhonn.refs, &v, in->vx, in->vy, in->yaw_rate, dw, tt, in->ay, r);
    } else if (kind == RH_CTRL_NMPC_RHONN) {
      rh_linear_refs_compute(&c->u.rhonn.linear, in->vx, in->vy, in->yaw_rate, dw, tt, in->ay,
                             r);
    } else {
      rh_linear_refs_compute(kind == RH_CTRL_NMPC_MF ? &c->u.mf.refs : &c->u.lmpc.refs, in->vx,
                             in->vy, in->yaw_rate, dw, tt, in->ay, r);
    }
    if (RH_FINITE(r[0] + r[1] + r[2])) {
      o->yaw_rate_ref = r[0];
      o->vy_ref = r[1];
      o->beta_ref = r[2];
    }
  }
  active = valid && in->stab_enable && in->vx >= c->v_min;
  {
    real_t dm = RH_R(0.0);
    int status = RH_QP_NOT_RUN, iters = 0, fb = 0;
    if (active) {
      real_t cap = rh_alloc_dm_capacity(&c->alloc, c->ctx.wheel_speeds);
      real_t cmax = c->dm_cap;
      rh_rollout_fn roll;
      const void *model;
      if (cmax > RH_R(0.0)) cap = cap < cmax ? cap : cmax;
      if (kind == RH_CTRL_NMPC_RHONN) {
        /* the box shrinks with the model confidence (0 while still learning) */
        c->confidence = rh_rhonn_model_confidence(&c->u.rhonn.model);
        cap = cap * c->confidence;
        roll = rollout_rhonn;
        model = &c->u.rhonn.model;
      } else if (kind == RH_CTRL_NMPC_MF) {
        roll = rollout_mf;
        model = &c->u.mf.model;
      } else {
        roll = rollout_lmpc;
        model = &c->u.lmpc.model;
      }
      {
        rh_qp_env_t env;
        double vx = (double)in->vx, mu = c->grip.mu;
        env.active = c->envelope && vx >= c->env_v_min;
        env.r_max = c->env_yaw_margin * mu * RH_GRIP_G / (vx > c->env_v_min ? vx : c->env_v_min);
        env.a_max = c->env_rear_slip_factor * atan(c->slip_per_mu * mu);
        env.ay = (double)in->ay;
        rh_qp_solve(&c->qp, roll, model, c->x, &c->ctx, o->yaw_rate_ref, o->beta_ref, -cap,
                    cap, c->dm_prev, &env, &dm, &status, &iters, &fb);
      }
    } else {
      int i;
      for (i = 0; i < RH_N_MAX; i++) c->qp.sol[i] = RH_R(0.0);
    }
    c->dm_held = dm;
    allocate(c, in, tt, dm, active);
    o->qp_status = status;
    o->qp_iterations = iters;
    o->fallback = fb;
  }
  /* one-step prediction with what is actually applied */
  c->ctx.total_torque = c->alloc.tt_applied;
  if (valid) {
    if (kind == RH_CTRL_NMPC_RHONN) {
      rh_rhonn_model_record(&c->u.rhonn.model, c->x, o->delta_m, &c->ctx, o->model_prediction);
    } else if (kind == RH_CTRL_NMPC_MF) {
      rh_seven_dof_predict(&c->u.mf.model, c->x, o->delta_m, &c->ctx, o->model_prediction);
    } else {
      rh_bicycle_predict(&c->u.lmpc.model, c->x, o->delta_m, &c->ctx, o->model_prediction);
    }
  } else {
    int i;
    if (kind == RH_CTRL_NMPC_RHONN) rh_rhonn_model_forget(&c->u.rhonn.model);
    for (i = 0; i < 3; i++) o->model_prediction[i] = (real_t)NAN;
  }
  *out = *o;
}

void rh_ctrl_allocate_only(rh_ctrl_t *c, const rh_inputs_t *in, rh_outputs_t *out) {
  real_t tt;
  int ok;
  if (c->kind == RH_CTRL_PASSIVE) {
    passive_step(c, in);
    *out = c->out;
    return;
  }
  copy_wheel_speeds(c, in);
  tt = rh_pedal_total_torque(in->accel_pedal, in->brake_pedal, c->peak_torque);
  ok = inputs_finite(in) && in->sensors_valid && in->stab_enable && in->vx >= c->v_min;
  allocate(c, in, tt, ok ? c->dm_held : RH_R(0.0), 0);
  c->out.qp_iterations = 0;
  *out = c->out;
}

void rh_ctrl_copy(rh_ctrl_t *dst, const rh_ctrl_t *src) {
  (void)memcpy(dst, src, sizeof *dst);
  if (src->kind != RH_CTRL_PASSIVE) rh_qp_copy(&dst->qp, &src->qp);
}

void rh_ctrl_sizes(int64_t out[2]) {
  out[0] = (int64_t)sizeof(rh_ctrl_t);
  out[1] = (int64_t)sizeof(rh_ctrl_config_t);
}
