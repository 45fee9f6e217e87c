/* SLCAN codec (see slcan.h). */
#include "slcan.h"

#include <string.h>

static const char HEX_DIGITS[] = "0123456789ABCDEF";

/* Value 0..15 of one hex digit (either case), or -1. */
static int hex_value(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  return -1;
}

/* Parse n hex digits of text into *value; 0 on success, -1 on a non-hex character. */
static int parse_hex(const char *text, size_t n, uint32_t *value) {
  uint32_t v = 0u;
  size_t i;
  for (i = 0u; i < n; i++) {
    int d = hex_value(text[i]);
    if (d < 0) return -1;
    v = (v << 4) | (uint32_t)d;
  }
  *value = v;
  return 0;
}

/* Parse a frame line (t, T, r, R) of len characters; 0 and *f filled, or -1. */
static int parse_frame(const char *line, size_t len, slcan_frame_t *f) {
  const int extended = (line[0] == 'T' || line[0] == 'R');
  const int rtr = (line[0] == 'r' || line[0] == 'R');
  const size_t id_digits = extended ? 8u : 3u;
  const uint32_t id_max = extended ? SLCAN_EXT_ID_MAX : SLCAN_STD_ID_MAX;
  uint32_t id, byte;
  int dlc;
  size_t i;

  if (len < 2u + id_digits) return -1;
  if (parse_hex(&line[1], id_digits, &id) != 0 || id > id_max) return -1;
  dlc = line[1u + id_digits] - '0';
  if (dlc < 0 || dlc > (int)SLCAN_DATA_MAX) return -1;
  /* a remote frame carries no data digits; a data frame exactly 2 per byte */
  if (len != 2u + id_digits + (rtr ? 0u : 2u * (size_t)dlc)) return -1;
  memset(f, 0, sizeof *f);
  f->id = id;
  f->extended = (uint8_t)extended;
  f->rtr = (uint8_t)rtr;
  f->dlc = (uint8_t)dlc;
  if (!rtr) {
    for (i = 0u; i < (size_t)dlc; i++) {
      if (parse_hex(&line[2u + id_digits + 2u * i], 2u, &byte) != 0) return -1;
      f->data[i] = (uint8_t)byte;
    }
  }
  return 0;
}

/* Set reply to text + '\r'; returns the length. */
static size_t answer(char reply[SLCAN_OUT_MAX], const char *text) {
  size_t n = 0u;
  while (text[n] != '\0') { /* the short constant answers: no strlen from the C library */
    reply[n] = text[n];
    n++;
  }
  reply[n] = SLCAN_CR;
  reply[n + 1u] = '\0';
  return n + 1u;
}

static size_t answer_error(char reply[SLCAN_OUT_MAX]) {
  reply[0] = SLCAN_BEL;
  reply[1] = '\0';
  return 1u;
}

/* Interpret the complete line s->line[0..len) and write its answer. */
static slcan_event_t interpret(slcan_t *s, slcan_frame_t *frame, char reply[SLCAN_OUT_MAX],
                               size_t *reply_len) {
  const char *line = s->line;
  const size_t len = s->len;
  const int closed = (s->mode == (uint8_t)SLCAN_CLOSED);
  char text[8];
  uint32_t unused;

  if (len == 0u) {
    *reply_len = answer(reply, "");
    return SLCAN_EV_COMMAND;
  }
  switch (line[0]) {
    case 't':
    case 'T':
    case 'r':
    case 'R':
      if (s->mode != (uint8_t)SLCAN_OPEN || parse_frame(line, len, frame) != 0) break;
      *reply_len = answer(reply, frame->extended ? "Z" : "z");
      return SLCAN_EV_FRAME;
    case 'S':
      if (!closed || len != 2u || line[1] < '0' || line[1] > '8') break;
      s->bitrate_code = (uint8_t)(line[1] - '0');
      *reply_len = answer(reply, "");
      return SLCAN_EV_COMMAND;
    case 's':
      if (!closed || len != 5u || parse_hex(&line[1], 4u, &unused) != 0) break;
      *reply_len = answer(reply, "");
      return SLCAN_EV_COMMAND;
    case 'O':
    case 'L':
      if (!closed || len != 1u) break;
      s->mode = (uint8_t)(line[0] == 'O' ? SLCAN_OPEN : SLCAN_LISTEN_ONLY);
      *reply_len = answer(reply, "");
      return SLCAN_EV_OPEN;
    case 'C':
      if (closed || len != 1u) break;
      s->mode = (uint8_t)SLCAN_CLOSED;
      *reply_len = answer(reply, "");
      return SLCAN_EV_CLOSE;
    case 'F':
      if (len != 1u) break;
      text[0] = 'F';
      text[1] = HEX_DIGITS[(s->status >> 4) & 0xFu];
      text[2] = HEX_DIGITS[s->status & 0xFu];
      text[3] = '\0';
      s->status = 0u;
      *reply_len = answer(reply, text);
      return SLCAN_EV_COMMAND;
    case 'V':
      if (len != 1u) break;
      *reply_len = answer(reply, "V" SLCAN_HW_VERSION SLCAN_SW_VERSION);
      return SLCAN_EV_COMMAND;
    case 'N':
      if (len != 1u) break;
      *reply_len = answer(reply, "N" SLCAN_SERIAL);
      return SLCAN_EV_COMMAND;
    case 'Z':
      if (!closed || len != 2u || line[1] != '0') break;
      *reply_len = answer(reply, "");
      return SLCAN_EV_COMMAND;
    default:
      break;
  }
  *reply_len = answer_error(reply);
  return SLCAN_EV_ERROR;
}

void slcan_init(slcan_t *s) {
  memset(s, 0, sizeof *s);
  s->mode = (uint8_t)SLCAN_CLOSED;
  s->bitrate_code = 6u;
}

slcan_event_t slcan_feed(slcan_t *s, uint8_t byte, slcan_frame_t *frame,
                         char reply[SLCAN_OUT_MAX], size_t *reply_len) {
  slcan_event_t ev;
  const uint8_t after_cr = s->after_cr;

  *reply_len = 0u;
  reply[0] = '\0';
  s->after_cr = 0u;
  if (byte == (uint8_t)'\n' && after_cr && s->len == 0u && !s->overlong) return SLCAN_EV_NONE;
  if (byte != (uint8_t)SLCAN_CR) {
    if (s->overlong) return SLCAN_EV_NONE;
    if (s->len >= SLCAN_LINE_MAX) {
      /* drop the whole line: skip to its '\r', answer that with one '\a' */
      s->overlong = 1u;
      return SLCAN_EV_NONE;
    }
    s->line[s->len++] = (char)byte;
    return SLCAN_EV_NONE;
  }
  s->after_cr = 1u;
  s->lines++;
  if (s->overlong) {
    ev = SLCAN_EV_ERROR;
    *reply_len = answer_error(reply);
    s->overlong_lines++;
    s->status |= SLCAN_STATUS_OVERRUN;
  } else {
    size_t i;
    ev = SLCAN_EV_NONE;
    for (i = 0u; i < s->len; i++) {
      /* printable ASCII only: a NUL or control byte inside a line is a corrupt line */
      if (s->line[i] < ' ' || s->line[i] > '~') ev = SLCAN_EV_ERROR;
    }
    if (ev == SLCAN_EV_ERROR) {
      *reply_len = answer_error(reply);
    } else {
      ev = interpret(s, frame, reply, reply_len);
    }
  }
  if (ev == SLCAN_EV_ERROR) s->errors++;
  s->len = 0u;
  s->overlong = 0u;
  return ev;
}

size_t slcan_format(const slcan_frame_t *frame, char out[SLCAN_OUT_MAX]) {
  const size_t id_digits = frame->extended ? 8u : 3u;
  const uint32_t id_max = frame->extended ? SLCAN_EXT_ID_MAX : SLCAN_STD_ID_MAX;
  size_t n = 0u, i;

  if (frame->id > id_max || frame->dlc > SLCAN_DATA_MAX) {
    out[0] = '\0';
    return 0u;
  }
  out[n++] = frame->rtr ? (frame->extended ? 'R' : 'r') : (frame->extended ? 'T' : 't');
  for (i = id_digits; i > 0u; i--) out[n++] = HEX_DIGITS[(frame->id >> (4u * (i - 1u))) & 0xFu];
  out[n++] = (char)('0' + frame->dlc);
  if (!frame->rtr) {
    for (i = 0u; i < frame->dlc; i++) {
      out[n++] = HEX_DIGITS[frame->data[i] >> 4];
      out[n++] = HEX_DIGITS[frame->data[i] & 0xFu];
    }
  }
  out[n++] = SLCAN_CR;
  out[n] = '\0';
  return n;
}

int slcan_is_open(const slcan_t *s) { return s->mode != (uint8_t)SLCAN_CLOSED; }
