/* tests/m7/m7_board.h - what the firmware's startup (startup.c) offers: semihosting console and exit. */
#ifndef DDYN_M7_BOARD_H
#define DDYN_M7_BOARD_H

void m7_puts(const char *s);
void m7_exit(int code) __attribute__((noreturn));

#endif
