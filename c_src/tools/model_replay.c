/*
 * ddyn_model_replay: one model step per input line, for cross-checks against Python.
 *
 * usage: ddyn_model_replay VEHICLE euler|rk4 < cases.txt
 * Each input line holds 27 numbers, x[8] u[2] c[17], separated by spaces; each
 * output line holds x_next[8] with 17 significant digits. A malformed line or a
 * model error stops the tool with a message naming the line, and exit status 1.
 * (`ddyn codegen check` drives it.)
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "ddyn/model.h"

#define LINE_MAX_CHARS 4096

static int parse_line(const char *line, double *values, int n)
{
    const char *p = line;
    char *end = NULL;
    int i;
    for (i = 0; i < n; ++i) {
        values[i] = strtod(p, &end);
        if (end == p) {
            return i;
        }
        p = end;
    }
    while (*p == ' ' || *p == '\t' || *p == '\r' || *p == '\n') {
        ++p;
    }
    return *p == '\0' ? n : -1;
}

int main(int argc, char **argv)
{
    static char line[LINE_MAX_CHARS];
    static ddyn_model_work work;
    const ddyn_vehicle_model *model;
    ddyn_discretisation disc;
    long line_no = 0;

    if (argc != 3) {
        fprintf(stderr, "usage: %s VEHICLE euler|rk4 < cases.txt\n", argv[0]);
        return 2;
    }
    model = ddyn_model_find(argv[1]);
    if (model == NULL) {
        fprintf(stderr, "ddyn_model_replay: no generated model for vehicle '%s'\n", argv[1]);
        return 2;
    }
    if (strcmp(argv[2], "euler") == 0) {
        disc = DDYN_DISC_EULER;
    } else if (strcmp(argv[2], "rk4") == 0) {
        disc = DDYN_DISC_RK4;
    } else {
        fprintf(stderr, "ddyn_model_replay: discretisation must be euler or rk4, got '%s'\n", argv[2]);
        return 2;
    }
    while (fgets(line, sizeof line, stdin) != NULL) {
        double v[DDYN_NX + DDYN_NU + DDYN_NC];
        double next[DDYN_NX];
        ddyn_status s;
        int i;
        ++line_no;
        if (parse_line(line, v, DDYN_NX + DDYN_NU + DDYN_NC) != DDYN_NX + DDYN_NU + DDYN_NC) {
            fprintf(stderr, "ddyn_model_replay: line %ld: expected %d numbers\n", line_no,
                    DDYN_NX + DDYN_NU + DDYN_NC);
            return 1;
        }
        s = ddyn_model_step(model, disc, v, v + DDYN_NX, v + DDYN_NX + DDYN_NU, next, &work);
        if (s != DDYN_OK) {
            fprintf(stderr, "ddyn_model_replay: line %ld: %s\n", line_no, ddyn_status_name(s));
            return 1;
        }
        for (i = 0; i < DDYN_NX; ++i) {
            printf(i + 1 < DDYN_NX ? "%.17g " : "%.17g\n", next[i]);
        }
    }
    return 0;
}
