/* QEMU TCG plugin (host shared object): counts executed guest instructions and logs the
 * running count each time the guest enters the marker function (address given as
 * `mark=0x...`). Output via qemu_plugin_outs: run QEMU with `-d plugin -D <log>`.
 *
 * Lines: "M <count>" at each marker entry (count = guest instructions executed before the
 * marker's first instruction), "T <count>" at exit.
 *
 * Counting is per translation block (n_insns added when a TB starts executing): exact for
 * straight-line bare-metal code without interrupts (the harness enables none). Debian's
 * QEMU ships no contrib plugins (libinsn.so), so this one is built with the host cc. The few
 * API declarations below are those of QEMU's include/qemu/qemu-plugin.h (stable from API
 * version 1, QEMU 6.0, on); the version number is -DPLUGIN_API_VERSION (default 1). */
#include <inttypes.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#ifndef PLUGIN_API_VERSION
#define PLUGIN_API_VERSION 1
#endif
#define EXPORT __attribute__((visibility("default")))

typedef uint64_t qemu_plugin_id_t;
struct qemu_plugin_tb;
struct qemu_info_t;
enum qemu_plugin_cb_flags { QEMU_PLUGIN_CB_NO_REGS, QEMU_PLUGIN_CB_R_REGS, QEMU_PLUGIN_CB_RW_REGS };
typedef void (*qemu_plugin_vcpu_tb_trans_cb_t)(qemu_plugin_id_t id, struct qemu_plugin_tb *tb);
typedef void (*qemu_plugin_vcpu_udata_cb_t)(unsigned int vcpu_index, void *userdata);
typedef void (*qemu_plugin_udata_cb_t)(qemu_plugin_id_t id, void *userdata);
void qemu_plugin_register_vcpu_tb_trans_cb(qemu_plugin_id_t id, qemu_plugin_vcpu_tb_trans_cb_t cb);
void qemu_plugin_register_vcpu_tb_exec_cb(struct qemu_plugin_tb *tb, qemu_plugin_vcpu_udata_cb_t cb,
                                          enum qemu_plugin_cb_flags flags, void *userdata);
size_t qemu_plugin_tb_n_insns(const struct qemu_plugin_tb *tb);
uint64_t qemu_plugin_tb_vaddr(const struct qemu_plugin_tb *tb);
void qemu_plugin_outs(const char *string);
void qemu_plugin_register_atexit_cb(qemu_plugin_id_t id, qemu_plugin_udata_cb_t cb, void *userdata);

EXPORT int qemu_plugin_version = PLUGIN_API_VERSION;

static uint64_t count;
static uint64_t mark_addr = UINT64_MAX;

static void on_tb(unsigned int vcpu, void *udata) {
  (void)vcpu;
  count += (uint64_t)(uintptr_t)udata;
}

static void on_mark(unsigned int vcpu, void *udata) {
  char buf[48];
  (void)vcpu;
  (void)udata;
  snprintf(buf, sizeof buf, "M %" PRIu64 "\n", count);
  qemu_plugin_outs(buf);
}

static void on_trans(qemu_plugin_id_t id, struct qemu_plugin_tb *tb) {
  size_t n = qemu_plugin_tb_n_insns(tb);
  (void)id;
  if ((qemu_plugin_tb_vaddr(tb) & ~(uint64_t)1) == mark_addr)
    qemu_plugin_register_vcpu_tb_exec_cb(tb, on_mark, QEMU_PLUGIN_CB_NO_REGS, NULL);
  qemu_plugin_register_vcpu_tb_exec_cb(tb, on_tb, QEMU_PLUGIN_CB_NO_REGS, (void *)(uintptr_t)n);
}

static void on_plugin_exit(qemu_plugin_id_t id, void *udata) {
  char buf[48];
  (void)id;
  (void)udata;
  snprintf(buf, sizeof buf, "T %" PRIu64 "\n", count);
  qemu_plugin_outs(buf);
}

EXPORT int qemu_plugin_install(qemu_plugin_id_t id, const struct qemu_info_t *info, int argc,
                               char **argv) {
  int i;
  (void)info;
  for (i = 0; i < argc; i++)
    if (strncmp(argv[i], "mark=", 5) == 0)
      mark_addr = strtoull(argv[i] + 5, NULL, 0) & ~(uint64_t)1;
  qemu_plugin_register_vcpu_tb_trans_cb(id, on_trans);
  qemu_plugin_register_atexit_cb(id, on_plugin_exit, NULL);
  return 0;
}
