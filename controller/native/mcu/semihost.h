/* Minimal ARM semihosting (SYS_WRITE0, SYS_EXIT) and output helpers for the MCU harness. */
#ifndef MCU_SEMIHOST_H
#define MCU_SEMIHOST_H

#include <stdint.h>

void sh_puts(const char *s);             /* SYS_WRITE0: NUL-terminated string to the host */
void sh_exit(int status) __attribute__((noreturn)); /* SYS_EXIT: 0 → host exit 0, else 1 */

/* Line buffer: append text / 8-digit hex / decimal, flush as one SYS_WRITE0. */
void ln_str(const char *s);
void ln_hex32(uint32_t v);
void ln_dec(uint32_t v);
void ln_flush(void);

#endif
