/*
 * ddyn_net_infer: guard-network inference on histories read from stdin (host tool).
 *
 * usage: ddyn_net_infer            each input line: DDYN_NET_TAU * 7 numbers (oldest row first);
 *                                  each output line: DDYN_NET_NOUT coefficients (%.17g)
 *        ddyn_net_infer --check    print the init status of the exported tables and of two
 *                                  tampered copies (another shape, another checkpoint hash)
 * Built against one export directory (ddyn_net_config.h + ddyn_net_weights.c).
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ddyn/guard_net.h"

extern const ddyn_net_tables ddyn_net_weights;

static int check(void)
{
    static ddyn_guard_net net;
    ddyn_net_tables other_shape = ddyn_net_weights;
    ddyn_net_tables other_hash = ddyn_net_weights;
    other_shape.tau += 1;
    other_hash.checkpoint_sha256 = "0000000000000000000000000000000000000000000000000000000000000000";
    printf("exported %s\n", ddyn_net_status_name(ddyn_guard_net_init(&net, &ddyn_net_weights)));
    printf("other_shape %s\n", ddyn_net_status_name(ddyn_guard_net_init(&net, &other_shape)));
    printf("other_hash %s\n", ddyn_net_status_name(ddyn_guard_net_init(&net, &other_hash)));
    return 0;
}

int main(int argc, char **argv)
{
    static ddyn_guard_net net;
    static char line[1 << 16];
    long line_no = 0;
    ddyn_net_status s;
    if (argc == 2 && strcmp(argv[1], "--check") == 0) {
        return check();
    }
    s = ddyn_guard_net_init(&net, &ddyn_net_weights);
    if (s != DDYN_NET_OK) {
        fprintf(stderr, "ddyn_net_infer: %s\n", ddyn_net_status_name(s));
        return 1;
    }
    while (fgets(line, sizeof line, stdin) != NULL) {
        double history[DDYN_NET_TAU][DDYN_NET_NFEAT];
        double coeffs[DDYN_NET_NOUT];
        char *p = line, *end = NULL;
        int i;
        ++line_no;
        for (i = 0; i < DDYN_NET_TAU * DDYN_NET_NFEAT; ++i) {
            history[i / DDYN_NET_NFEAT][i % DDYN_NET_NFEAT] = strtod(p, &end);
            if (end == p) {
                fprintf(stderr, "ddyn_net_infer: line %ld: expected %d numbers\n", line_no,
                        DDYN_NET_TAU * DDYN_NET_NFEAT);
                return 1;
            }
            p = end;
        }
        s = ddyn_guard_net_infer(&net, (const double(*)[DDYN_NET_NFEAT])history, coeffs);
        if (s != DDYN_NET_OK) {
            fprintf(stderr, "ddyn_net_infer: line %ld: %s\n", line_no, ddyn_net_status_name(s));
            return 1;
        }
        for (i = 0; i < DDYN_NET_NOUT; ++i) {
            printf(i + 1 < DDYN_NET_NOUT ? "%.17g " : "%.17g\n", coeffs[i]);
        }
    }
    return 0;
}
