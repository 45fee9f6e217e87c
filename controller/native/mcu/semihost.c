/* ARM semihosting over BKPT 0xAB (Thumb / M-profile). QEMU: -semihosting-config enable=on. */
#include "semihost.h"

#define SYS_WRITE0 0x04
#define SYS_EXIT 0x18
#define ADP_Stopped_ApplicationExit 0x20026
#define ADP_Stopped_RunTimeErrorUnknown 0x20023

static int sh_call(int op, const void *arg) {
  register int r0 __asm__("r0") = op;
  register const void *r1 __asm__("r1") = arg;
  __asm__ volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
  return r0;
}

void sh_puts(const char *s) { (void)sh_call(SYS_WRITE0, s); }

void sh_exit(int status) {
  /* AArch32 SYS_EXIT takes the reason code itself in r1 (QEMU: ApplicationExit → 0, else 1). */
  (void)sh_call(SYS_EXIT, (const void *)(uintptr_t)(status == 0 ? ADP_Stopped_ApplicationExit
                                                                 : ADP_Stopped_RunTimeErrorUnknown));
  for (;;) {
  }
}

static char line[128]; /* flushed when full: a longer line goes out in pieces */
static unsigned line_len;

static void ln_putc(char c) {
  if (line_len + 2 >= sizeof line) ln_flush();
  line[line_len++] = c;
}

void ln_str(const char *s) {
  while (*s) ln_putc(*s++);
}

void ln_hex32(uint32_t v) {
  static const char HEX[] = "0123456789abcdef";
  int i;
  for (i = 28; i >= 0; i -= 4) ln_putc(HEX[(v >> i) & 0xfu]);
}

void ln_dec(uint32_t v) {
  char buf[11];
  int n = 0;
  do {
    buf[n++] = (char)('0' + v % 10u);
    v /= 10u;
  } while (v);
  while (n) ln_putc(buf[--n]);
}

void ln_flush(void) {
  if (!line_len) return;
  line[line_len] = '\0';
  sh_puts(line);
  line_len = 0;
}
