/* The one thin CPython binding of the C core (controller/native/include/rhonn_core.h).
 *
 * Built twice by setup.py: as controller.native._rhcore64 (real_t = double) and
 * controller.native._rhcore32 (-DRH_FLOAT32). A Core object owns one rh_ctrl_t:
 *   Core(config_bytes, outputs)  rh_ctrl_init from the bytes of an rh_ctrl_config_t;
 *                                outputs: the ControllerOutputs object step() fills
 *   step(inputs) / allocate_only(inputs) -> outputs   (inputs: a ControllerInputs)
 *   reset(), copy_from(other), warm_start(x, y), sizes(), offsets()
 * The object exposes the state struct through the buffer protocol (read/write), so the
 * Python side reads counters and learned state, and restores checkpoints, without more C.
 * Bad numbers never raise: a non-numeric input reads as NaN (the core then rejects it). */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stddef.h>
#include <structmember.h>
#include <string.h>

#include "rhonn_core.h"

#ifdef RH_FLOAT32
#define MODULE_NAME "_rhcore32"
#define INIT_FN PyInit__rhcore32
#else
#define MODULE_NAME "_rhcore64"
#define INIT_FN PyInit__rhcore64
#endif

enum { A_SWA, A_ACC, A_BRK, A_YAW, A_AX, A_AY, A_WS, A_VX, A_VY, A_STAB, A_VALID, A_TORQ,
       A_TT, A_DM, A_RREF, A_VYREF, A_BREF, A_STATUS, A_ITERS, A_FB, A_PRED, A_N };
static const char *ATTR_NAMES[A_N] = {
    "swa_rad", "accel_pedal", "brake_pedal", "yaw_rate", "ax", "ay", "wheel_speeds", "vx",
    "vy", "stab_enable", "sensors_valid", "torques", "total_torque", "delta_m",
    "yaw_rate_ref", "vy_ref", "beta_ref", "qp_status", "qp_iterations", "fallback",
    "model_prediction"};
static PyObject *attr[A_N];

/* Slot offsets of a __slots__ class's attributes (ControllerInputs / ControllerOutputs are
 * slotted dataclasses): reading and writing those slots directly skips the attribute
 * lookup; any other type goes through getattr/setattr. off[k] < 0: not a plain slot. */
typedef struct {
  PyTypeObject *type;
  Py_ssize_t off[A_N];
} slot_map_t;

static void map_slots(slot_map_t *m, PyTypeObject *type, int first, int last) {
  int k;
  Py_INCREF(type); /* held: a freed type's address must not match a later one */
  Py_XSETREF(m->type, type);
  for (k = 0; k < A_N; k++) m->off[k] = -1;
  for (k = first; k <= last; k++) {
    PyObject *d = PyObject_GetAttr((PyObject *)type, attr[k]);
    if (d == NULL) {
      PyErr_Clear();
      continue;
    }
    if (Py_IS_TYPE(d, &PyMemberDescr_Type)) {
      PyMemberDef *md = ((PyMemberDescrObject *)d)->d_member;
      if (md->type == T_OBJECT_EX && !(md->flags & READONLY)) m->off[k] = md->offset;
    }
    Py_DECREF(d);
  }
}

/* New reference to attribute k of obj, or NULL (no error set) when it is missing. */
static PyObject *get_attr(const slot_map_t *m, PyObject *obj, int k) {
  PyObject *v;
  if (Py_TYPE(obj) == m->type && m->off[k] >= 0) {
    v = *(PyObject **)((char *)obj + m->off[k]);
    Py_XINCREF(v);
    return v;
  }
  v = PyObject_GetAttr(obj, attr[k]);
  if (v == NULL) PyErr_Clear();
  return v;
}

/* Set attribute k of obj to v (steals the reference); -1 on error. */
static int set_attr(const slot_map_t *m, PyObject *obj, int k, PyObject *v) {
  int rc;
  if (v == NULL) return -1;
  if (Py_TYPE(obj) == m->type && m->off[k] >= 0) {
    Py_XSETREF(*(PyObject **)((char *)obj + m->off[k]), v);
    return 0;
  }
  rc = PyObject_SetAttr(obj, attr[k], v);
  Py_DECREF(v);
  return rc;
}

typedef struct {
  PyObject_HEAD
  slot_map_t in_map;       /* slots of the last inputs type seen */
  slot_map_t out_map;      /* slots of the outputs type */
  PyObject *ws_obj;        /* the last wheel-speed array read (its buffer held in ws_buf) */
  Py_buffer ws_buf;
  PyObject *outputs;       /* the ControllerOutputs object step() fills */
  Py_buffer torques;       /* its torques array (float64, 4) */
  Py_buffer prediction;    /* its model_prediction array (float64, 3) */
  int exports;             /* live buffer exports of the state */
  rh_ctrl_t ctrl;
} CoreObject;

static PyTypeObject CoreType;

static double read_float(const slot_map_t *m, PyObject *obj, int k) {
  PyObject *v = get_attr(m, obj, k);
  double d;
  if (v == NULL) return (double)NAN;
  if (PyFloat_CheckExact(v)) {
    d = PyFloat_AS_DOUBLE(v);
  } else {
    d = PyFloat_AsDouble(v);
    if (d == -1.0 && PyErr_Occurred()) {
      PyErr_Clear();
      d = (double)NAN;
    }
  }
  Py_DECREF(v);
  return d;
}

static int read_bool(const slot_map_t *m, PyObject *obj, int k) {
  PyObject *v = get_attr(m, obj, k);
  int b;
  if (v == NULL) return 0;
  b = v == Py_True ? 1 : (v == Py_False ? 0 : PyObject_IsTrue(v));
  Py_DECREF(v);
  if (b < 0) {
    PyErr_Clear();
    return 0;
  }
  return b;
}

static void release_ws(CoreObject *self) {
  if (self->ws_obj != NULL) {
    PyBuffer_Release(&self->ws_buf);
    self->ws_obj = NULL;
  }
}

/* Four wheel speeds from a float64 buffer or any sequence of 4 numbers; 0 if unusable. The
 * node writes its array in place, so the buffer of the last array is kept (a held buffer
 * also stops numpy from resizing it) and re-read while the attribute is the same object. */
static int read_wheel_speeds(CoreObject *self, PyObject *obj, real_t ws[4]) {
  PyObject *v = get_attr(&self->in_map, obj, A_WS);
  int ok = 0, i;
  if (v == NULL) return 0;
  if (v != self->ws_obj) {
    release_ws(self);
    if (PyObject_CheckBuffer(v) &&
        PyObject_GetBuffer(v, &self->ws_buf, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) == 0) {
      if (self->ws_buf.format && strcmp(self->ws_buf.format, "d") == 0 &&
          self->ws_buf.len == 4 * (Py_ssize_t)sizeof(double))
        self->ws_obj = v; /* held through ws_buf.obj */
      else
        PyBuffer_Release(&self->ws_buf);
    } else {
      PyErr_Clear();
    }
  }
  if (v == self->ws_obj) {
    const double *d = (const double *)self->ws_buf.buf;
    for (i = 0; i < 4; i++) ws[i] = (real_t)d[i];
    ok = 1;
  }
  if (!ok) {
    PyObject *seq = PySequence_Fast(v, "");
    if (seq != NULL && PySequence_Fast_GET_SIZE(seq) == 4) {
      ok = 1;
      for (i = 0; i < 4; i++) {
        double d = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(seq, i));
        if (d == -1.0 && PyErr_Occurred()) {
          PyErr_Clear();
          ok = 0;
          break;
        }
        ws[i] = (real_t)d;
      }
    }
    Py_XDECREF(seq);
    PyErr_Clear();
  }
  Py_DECREF(v);
  if (!ok)
    for (i = 0; i < 4; i++) ws[i] = RH_R(0.0);
  return ok;
}

static void read_inputs(CoreObject *self, PyObject *obj, rh_inputs_t *in) {
  const slot_map_t *m = &self->in_map;
  if (Py_TYPE(obj) != m->type) map_slots(&self->in_map, Py_TYPE(obj), A_SWA, A_VALID);
  in->swa_rad = (real_t)read_float(m, obj, A_SWA);
  in->accel_pedal = (real_t)read_float(m, obj, A_ACC);
  in->brake_pedal = (real_t)read_float(m, obj, A_BRK);
  in->yaw_rate = (real_t)read_float(m, obj, A_YAW);
  in->ax = (real_t)read_float(m, obj, A_AX);
  in->ay = (real_t)read_float(m, obj, A_AY);
  in->vx = (real_t)read_float(m, obj, A_VX);
  in->vy = (real_t)read_float(m, obj, A_VY);
  in->wheel_speeds_usable = read_wheel_speeds(self, obj, in->wheel_speeds);
  in->stab_enable = read_bool(m, obj, A_STAB);
  in->sensors_valid = read_bool(m, obj, A_VALID);
}


static PyObject *write_outputs(CoreObject *self, const rh_outputs_t *out) {
  PyObject *o = self->outputs;
  double *t = (double *)self->torques.buf, *p = (double *)self->prediction.buf;
  int i;
  for (i = 0; i < 4; i++) t[i] = (double)out->torques[i];
  for (i = 0; i < 3; i++) p[i] = (double)out->model_prediction[i];
  const slot_map_t *m = &self->out_map;
  if (set_attr(m, o, A_TT, PyFloat_FromDouble((double)out->total_torque)) < 0 ||
      set_attr(m, o, A_DM, PyFloat_FromDouble((double)out->delta_m)) < 0 ||
      set_attr(m, o, A_RREF, PyFloat_FromDouble((double)out->yaw_rate_ref)) < 0 ||
      set_attr(m, o, A_VYREF, PyFloat_FromDouble((double)out->vy_ref)) < 0 ||
      set_attr(m, o, A_BREF, PyFloat_FromDouble((double)out->beta_ref)) < 0 ||
      set_attr(m, o, A_STATUS, PyLong_FromLong(out->qp_status)) < 0 ||
      set_attr(m, o, A_ITERS, PyLong_FromLong(out->qp_iterations)) < 0 ||
      set_attr(m, o, A_FB, Py_NewRef(out->fallback ? Py_True : Py_False)) < 0)
    return NULL;
  Py_INCREF(o);
  return o;
}

static int get_array(PyObject *outputs, PyObject *name, Py_ssize_t n, Py_buffer *b) {
  PyObject *a = PyObject_GetAttr(outputs, name);
  int rc;
  if (a == NULL) return -1;
  rc = PyObject_GetBuffer(a, b, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE);
  Py_DECREF(a);
  if (rc < 0) return -1;
  if (b->format == NULL || strcmp(b->format, "d") != 0 ||
      b->len != n * (Py_ssize_t)sizeof(double)) {
    PyBuffer_Release(b);
    PyErr_Format(PyExc_TypeError, "outputs.%U must be a writable float64 array of %zd",
                 name, n);
    return -1;
  }
  return 0;
}

static int bind_outputs(CoreObject *self, PyObject *outputs) {
  if (get_array(outputs, attr[A_TORQ], 4, &self->torques) < 0) return -1;
  if (get_array(outputs, attr[A_PRED], 3, &self->prediction) < 0) {
    PyBuffer_Release(&self->torques);
    return -1;
  }
  Py_INCREF(outputs);
  self->outputs = outputs;
  map_slots(&self->out_map, Py_TYPE(outputs), A_TT, A_FB);
  return 0;
}

static PyObject *Core_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
  CoreObject *self;
  Py_buffer cfg;
  PyObject *outputs;
  int rc;
  static char *kwlist[] = {"config", "outputs", NULL};
  if (!PyArg_ParseTupleAndKeywords(args, kwds, "y*O", kwlist, &cfg, &outputs)) return NULL;
  if (cfg.len != (Py_ssize_t)sizeof(rh_ctrl_config_t)) {
    PyErr_Format(PyExc_ValueError, "config: expected %zd bytes (rh_ctrl_config_t), got %zd",
                 (Py_ssize_t)sizeof(rh_ctrl_config_t), cfg.len);
    PyBuffer_Release(&cfg);
    return NULL;
  }
  self = (CoreObject *)type->tp_alloc(type, 0);
  if (self == NULL) {
    PyBuffer_Release(&cfg);
    return NULL;
  }
  rc = rh_ctrl_init(&self->ctrl, (const rh_ctrl_config_t *)cfg.buf);
  PyBuffer_Release(&cfg);
  if (rc != 0) {
    Py_DECREF(self);
    PyErr_Format(PyExc_ValueError, rc == -2 ? "no generated QP solver for this horizon/shape "
                                              "in this build (horizon 1..%d)"
                                            : "invalid controller configuration (code %d)",
                 rc == -2 ? RH_N_MAX : rc);
    return NULL;
  }
  if (bind_outputs(self, outputs) < 0) {
    Py_DECREF(self);
    return NULL;
  }
  return (PyObject *)self;
}

static void Core_dealloc(CoreObject *self) {
  release_ws(self);
  Py_CLEAR(self->in_map.type);
  Py_CLEAR(self->out_map.type);
  if (self->outputs != NULL) {
    PyBuffer_Release(&self->torques);
    PyBuffer_Release(&self->prediction);
    Py_CLEAR(self->outputs);
  }
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject *Core_step(CoreObject *self, PyObject *inputs) {
  rh_inputs_t in;
  rh_outputs_t out;
  read_inputs(self, inputs, &in);
  rh_ctrl_step(&self->ctrl, &in, &out);
  return write_outputs(self, &out);
}

static PyObject *Core_allocate_only(CoreObject *self, PyObject *inputs) {
  rh_inputs_t in;
  rh_outputs_t out;
  read_inputs(self, inputs, &in);
  rh_ctrl_allocate_only(&self->ctrl, &in, &out);
  return write_outputs(self, &out);
}

static PyObject *Core_reset(CoreObject *self, PyObject *Py_UNUSED(arg)) {
  rh_ctrl_reset(&self->ctrl);
  Py_RETURN_NONE;
}

static PyObject *Core_copy_from(CoreObject *self, PyObject *other) {
  if (!PyObject_TypeCheck(other, &CoreType)) {
    PyErr_SetString(PyExc_TypeError, "copy_from expects a Core");
    return NULL;
  }
  rh_ctrl_copy(&self->ctrl, &((CoreObject *)other)->ctrl);
  Py_RETURN_NONE;
}

/* warm_start(x or None, y or None): OSQP warm start in decision units. */
static PyObject *Core_warm_start(CoreObject *self, PyObject *args) {
  PyObject *xo, *yo;
  Py_buffer xb, yb;
  const double *x = NULL, *y = NULL;
  if (!PyArg_ParseTuple(args, "OO", &xo, &yo)) return NULL;
  if (self->ctrl.cfg.kind == RH_CTRL_PASSIVE) Py_RETURN_NONE;
  if (xo != Py_None) {
    if (PyObject_GetBuffer(xo, &xb, PyBUF_C_CONTIGUOUS) < 0) return NULL;
    if (xb.len != self->ctrl.qp.N * (Py_ssize_t)sizeof(double)) {
      PyBuffer_Release(&xb);
      return PyErr_Format(PyExc_ValueError, "x: expected %d float64", self->ctrl.qp.N);
    }
    x = (const double *)xb.buf;
  }
  if (yo != Py_None) {
    if (PyObject_GetBuffer(yo, &yb, PyBUF_C_CONTIGUOUS) < 0) {
      if (x) PyBuffer_Release(&xb);
      return NULL;
    }
    if (yb.len != self->ctrl.qp.m * (Py_ssize_t)sizeof(double)) {
      PyBuffer_Release(&yb);
      if (x) PyBuffer_Release(&xb);
      return PyErr_Format(PyExc_ValueError, "y: expected %d float64", self->ctrl.qp.m);
    }
    y = (const double *)yb.buf;
  }
  rh_qp_warm_start(&self->ctrl.qp, x, y);
  if (x) PyBuffer_Release(&xb);
  if (y) PyBuffer_Release(&yb);
  Py_RETURN_NONE;
}

static PyObject *Core_sizes(PyObject *Py_UNUSED(cls), PyObject *Py_UNUSED(arg)) {
  int64_t s[2];
  rh_ctrl_sizes(s);
  return Py_BuildValue("(LLi)", (long long)s[0], (long long)s[1], (int)sizeof(real_t));
}

#define OFF(name, member) PyDict_SetItemString(d, name, v = PyLong_FromSsize_t((Py_ssize_t)offsetof(rh_ctrl_t, member))), Py_DECREF(v)

/* Byte offsets of the fields the Python side reads and writes (from offsetof: the layout
 * is the compiler's, never assumed). */
static PyObject *Core_offsets(PyObject *Py_UNUSED(cls), PyObject *Py_UNUSED(arg)) {
  PyObject *d = PyDict_New(), *v;
  if (d == NULL) return NULL;
  OFF("out", out);
  OFF("dm_held", dm_held);
  OFF("dm_prev", dm_prev);
  OFF("confidence", confidence);
  OFF("steps", steps);
  OFF("invalid_steps", invalid_steps);
  OFF("alloc", alloc);
  OFF("alloc.tt_applied", alloc.tt_applied);
  OFF("alloc.dm_applied", alloc.dm_applied);
  OFF("qp", qp);
  OFF("grip.mu", grip.mu);
  OFF("grip.shown", grip.shown);
  OFF("grip.saturation", grip.saturation);
  OFF("grip.grip_used", grip.grip_used);
  OFF("gdemand.factor_last", gdemand.factor_last);
  OFF("gdemand.weight_last", gdemand.weight_last);
  OFF("gdemand.guard.active_calls", gdemand.guard.active_calls);
  OFF("qp.slack", qp.slack);
  OFF("alloc.prev", alloc.prev);
  OFF("alloc.rate_limited_calls", alloc.rate_limited_calls);
  OFF("qp.sol", qp.sol);
  OFF("qp.ubar", qp.ubar);
  OFF("qp.y_last", qp.y_last);
  OFF("qp.has_y_last", qp.has_y_last);
  OFF("qp.zprev", qp.zprev);
  OFF("qp.last_iterations", qp.last_iterations);
  OFF("qp.worst_iterations", qp.worst_iterations);
  OFF("qp.max_iter_hits", qp.max_iter_hits);
  OFF("qp.fallbacks", qp.fallbacks);
  OFF("qp.last_status", qp.last_status);
  OFF("qp.N", qp.N);
  OFF("qp.m", qp.m);
  OFF("rhonn.model", u.rhonn.model);
  OFF("rhonn.model.err_ms", u.rhonn.model.err_ms);
  OFF("rhonn.model.learn_steps", u.rhonn.model.learn_steps);
  OFF("rhonn.model.gate_open", u.rhonn.model.gate_open);
  OFF("rhonn.model.has_record", u.rhonn.model.has_record);
  OFF("rhonn.model.rec_phi", u.rhonn.model.rec_phi);
  OFF("rhonn.model.rec_chi", u.rhonn.model.rec_chi);
  OFF("rhonn.ekf", u.rhonn.model.f.std);
  OFF("rhonn.ekf.W", u.rhonn.model.f.std.W);
  OFF("rhonn.ekf.P", u.rhonn.model.f.std.P);
  OFF("rhonn.ekf.counters", u.rhonn.model.f.std.counters);
  OFF("rhonn.ekf.since_eig", u.rhonn.model.f.std.since_eig);
  OFF("rhonn.ud", u.rhonn.model.f.ud);
  OFF("rhonn.ud.W", u.rhonn.model.f.ud.W);
  OFF("rhonn.ud.U", u.rhonn.model.f.ud.U);
  OFF("rhonn.ud.D", u.rhonn.model.f.ud.D);
  OFF("rhonn.ud.counters", u.rhonn.model.f.ud.counters);
  OFF("rhonn.refs", u.rhonn.refs);
  return d;
}

/* buffer protocol: the rh_ctrl_t bytes, writable */
static int Core_getbuffer(CoreObject *self, Py_buffer *view, int flags) {
  int rc = PyBuffer_FillInfo(view, (PyObject *)self, &self->ctrl, sizeof(rh_ctrl_t), 0, flags);
  if (rc == 0) self->exports += 1;
  return rc;
}

static void Core_releasebuffer(CoreObject *self, Py_buffer *Py_UNUSED(view)) {
  self->exports -= 1;
}

static PyBufferProcs Core_as_buffer = {(getbufferproc)Core_getbuffer,
                                       (releasebufferproc)Core_releasebuffer};

static PyMethodDef Core_methods[] = {
    {"step", (PyCFunction)Core_step, METH_O, "One MPC period; fills and returns outputs."},
    {"allocate_only", (PyCFunction)Core_allocate_only, METH_O,
     "Re-allocate the held Delta M with the fresh pedal torque."},
    {"reset", (PyCFunction)Core_reset, METH_NOARGS, "Cold start."},
    {"copy_from", (PyCFunction)Core_copy_from, METH_O,
     "Become a copy of another Core (same config) that runs on bit for bit."},
    {"warm_start", (PyCFunction)Core_warm_start, METH_VARARGS,
     "OSQP warm start from x (N,) and y (m,) float64, decision units (None = unchanged)."},
    {"sizes", (PyCFunction)Core_sizes, METH_NOARGS | METH_CLASS,
     "(sizeof rh_ctrl_t, sizeof rh_ctrl_config_t, sizeof real_t)"},
    {"offsets", (PyCFunction)Core_offsets, METH_NOARGS | METH_CLASS,
     "Byte offsets of named fields of rh_ctrl_t."},
    {NULL, NULL, 0, NULL}};

static PyTypeObject CoreType = {
    PyVarObject_HEAD_INIT(NULL, 0) MODULE_NAME ".Core", /* tp_name */
    sizeof(CoreObject),                                 /* tp_basicsize */
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, MODULE_NAME,
                                    "The C controller core (rhonn_core.h).", -1, NULL,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC INIT_FN(void) {
  PyObject *m;
  int i;
  for (i = 0; i < A_N; i++) {
    attr[i] = PyUnicode_InternFromString(ATTR_NAMES[i]);
    if (attr[i] == NULL) return NULL;
  }
  CoreType.tp_dealloc = (destructor)Core_dealloc;
  CoreType.tp_flags = Py_TPFLAGS_DEFAULT;
  CoreType.tp_doc = "One controller of the C core (rh_ctrl_t).";
  CoreType.tp_methods = Core_methods;
  CoreType.tp_new = Core_new;
  CoreType.tp_as_buffer = &Core_as_buffer;
  if (PyType_Ready(&CoreType) < 0) return NULL;
  m = PyModule_Create(&module);
  if (m == NULL) return NULL;
  Py_INCREF(&CoreType);
  if (PyModule_AddObject(m, "Core", (PyObject *)&CoreType) < 0) {
    Py_DECREF(&CoreType);
    Py_DECREF(m);
    return NULL;
  }
  return m;
}
