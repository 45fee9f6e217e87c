/* SLCAN codec: the Lawicel ASCII protocol of USB-CAN adapters (CANUSB / CAN232), adapter side.
 *
 * Pure C99, no I/O, static memory: the caller owns an slcan_t and feeds it the bytes received
 * from the host one at a time; every line the host ends with '\r' gets exactly one answer
 * (written into the caller's reply buffer), and a complete CAN frame line is handed back as
 * an slcan_frame_t. Frames from the bus to the host are formatted with slcan_format.
 *
 * Lines understood (hex digits upper or lower case; the answer in brackets, '\a' = BEL 0x07):
 *   tiiildd..\r        standard frame, iii <= 7FF, l = DLC 0..8, 2l data digits  [z\r]
 *   Tiiiiiiiildd..\r   extended frame, iiiiiiii <= 1FFFFFFF                      [Z\r]
 *   riiil\r / Riiiiiiiil\r   remote (RTR) frame, standard / extended             [z\r / Z\r]
 *   Sn\r               bit rate n = 0..8 (10k..1M), channel closed only          [\r]
 *   sxxyy\r            BTR0/BTR1 bit timing, channel closed only                 [\r]
 *   O\r / L\r          open the channel (normal / listen only), closed only      [\r]
 *   C\r                close the channel, open only                              [\r]
 *   F\r                status flags (bit 3: a receive line was lost)             [Fxx\r]
 *   V\r                hardware / software version                               [Vhhss\r]
 *   N\r                serial number                                             [Nxxxx\r]
 *   Z0\r               time stamps off (Z1, time stamps on, is not supported)    [\r]
 *   \r                 empty line (a no-op the host may send to resynchronise)   [\r]
 * Any other line, a frame while the channel is closed, a frame in listen-only mode, a command
 * in the wrong channel state, or a line longer than SLCAN_LINE_MAX characters gets '\a'. An
 * overlong line is dropped whole: bytes are discarded up to the next '\r', which then gets
 * the single '\a' (the codec is back in step at the next line). A '\n' right after a line end
 * (terminals that send "\r\n") is ignored.
 *
 * Reference: LAWICEL CANUSB / CAN232 ASCII command set (lawicel.com, "CANUSB Manual",
 * "CAN232 Manual"), as implemented by python-can's slcan interface. */
#ifndef PIL_SLCAN_H
#define PIL_SLCAN_H

#include <stddef.h>
#include <stdint.h>

#define SLCAN_DATA_MAX 8u
#define SLCAN_STD_ID_MAX 0x7FFu
#define SLCAN_EXT_ID_MAX 0x1FFFFFFFu
/* Longest legal line without its '\r': "T" + 8 id + 1 DLC + 16 data digits. */
#define SLCAN_LINE_MAX 26u
/* Longest answer or formatted frame, '\r' and a terminating NUL included. */
#define SLCAN_OUT_MAX 28u

#define SLCAN_BEL '\a'
#define SLCAN_CR '\r'

/* F\r status flag bits (CANUSB manual): bit 3 = data overrun (here: a lost receive line). */
#define SLCAN_STATUS_OVERRUN 0x08u

/* Version and serial number answered to V and N (ASCII digits as the manual shows them). */
#define SLCAN_HW_VERSION "10"
#define SLCAN_SW_VERSION "01"
#define SLCAN_SERIAL "RH01"

/* One classic CAN frame. */
typedef struct {
  uint32_t id;       /* 11-bit (extended 0) or 29-bit (extended 1) identifier */
  uint8_t extended;  /* 1: 29-bit identifier */
  uint8_t rtr;       /* 1: remote transmission request (no data) */
  uint8_t dlc;       /* data length code 0..8 (bytes) */
  uint8_t data[SLCAN_DATA_MAX];
} slcan_frame_t;

/* What a completed line was. */
typedef enum {
  SLCAN_EV_NONE = 0,   /* no line completed by this byte */
  SLCAN_EV_FRAME,      /* a frame for the bus: *frame is filled, the answer is z\r / Z\r */
  SLCAN_EV_OPEN,       /* O or L accepted: the channel is open */
  SLCAN_EV_CLOSE,      /* C accepted: the channel is closed */
  SLCAN_EV_COMMAND,    /* another command accepted (S, s, F, V, N, Z0, empty line) */
  SLCAN_EV_ERROR       /* the line was refused: the answer is '\a' */
} slcan_event_t;

typedef enum {
  SLCAN_CLOSED = 0,
  SLCAN_OPEN,         /* normal: frames both ways */
  SLCAN_LISTEN_ONLY   /* receive only: frames from the host are refused */
} slcan_mode_t;

/* Codec state (caller-owned, no pointers: copyable). */
typedef struct {
  char line[SLCAN_LINE_MAX];  /* the line being received, without '\r' */
  uint8_t len;                /* characters in line */
  uint8_t overlong;           /* 1: the current line exceeded SLCAN_LINE_MAX, skipping to '\r' */
  uint8_t after_cr;           /* 1: the previous byte ended a line (a following '\n' is ignored) */
  uint8_t mode;               /* slcan_mode_t */
  uint8_t bitrate_code;       /* last S code 0..8 (default 6 = 500 kbit/s) */
  uint8_t status;             /* F flags, cleared when read */
  uint32_t lines;             /* lines completed */
  uint32_t errors;            /* lines answered with '\a' */
  uint32_t overlong_lines;    /* lines dropped for length */
} slcan_t;

/* Reset to: channel closed, 500 kbit/s, no partial line, counters zero. */
void slcan_init(slcan_t *s);

/* Feed one byte from the host. When it completes a line, the line's answer is written to
 * reply (NUL-terminated, at most SLCAN_OUT_MAX bytes with the NUL) and *reply_len is set to
 * its length (without the NUL), a frame line fills *frame, and the event is returned; else
 * SLCAN_EV_NONE with *reply_len = 0. NUL bytes and other control characters inside a line
 * make the line an error. */
slcan_event_t slcan_feed(slcan_t *s, uint8_t byte, slcan_frame_t *frame,
                         char reply[SLCAN_OUT_MAX], size_t *reply_len);

/* Format a frame from the bus for the host ("t1238112233..\r", "T...", "r...", "R..."),
 * NUL-terminated into out; returns the length without the NUL, or 0 for an invalid frame
 * (identifier out of range, DLC > 8). */
size_t slcan_format(const slcan_frame_t *frame, char out[SLCAN_OUT_MAX]);

/* 1 when frames may go to the host (the channel is open or listen-only), else 0. */
int slcan_is_open(const slcan_t *s);

#endif /* PIL_SLCAN_H */
