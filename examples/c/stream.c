/* Stream a CSV of IMU samples (one sample per line: gyro x,y,z [rad/s], acc x,y,z [m/s^2]
 * (, mag x,y,z [uT])) through a C runtime generated from a checkpoint, print one line per sample
 * "w,x,y,z,omega_x,omega_y,omega_z" (refused samples: "refused,<code>") and, on stderr, the
 * median per-sample step time.
 *
 *   tcn-ahrs export ckpt=checkpoints/broad9_residual.ckpt format=c out=broad9.c
 *   cc -std=c99 -O2 -Wall -Wextra -DMODEL=broad9 -DMODEL_HEADER='"broad9.h"' stream.c broad9.c -o stream -lm
 *   ./stream imu.csv 0.005 [q0w q0x q0y q0z] > quat.csv
 *
 * (or: make MODEL=broad9, see the Makefile). Add -DTCN_AHRS_REAL=double for a double backbone. */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include MODEL_HEADER

#define CAT_(a, b) a##_##b
#define CAT(a, b) CAT_(a, b)
#define API(x) CAT(MODEL, x)
#define AXES API(AXES)

static int cmp(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv)
{
    static API(state) st;   /* static memory: the runtime allocates nothing */
    float q0[4] = {1.0f, 0.0f, 0.0f, 0.0f}, x[AXES], q[4], w[3], dt;
    double *times = NULL;
    size_t n = 0, cap = 0, refused = 0;
    char line[4096];
    FILE *f;
    int i, code;
    if (argc != 3 && argc != 7) {
        fprintf(stderr, "usage: %s samples.csv dt [q0w q0x q0y q0z]\n", argv[0]);
        return 2;
    }
    dt = strtof(argv[2], NULL);
    if (argc == 7)
        for (i = 0; i < 4; i++) q0[i] = strtof(argv[3 + i], NULL);
    if (API(init)(&st, q0) != 0) {
        fprintf(stderr, "bad q0\n");
        return 2;
    }
    f = fopen(argv[1], "r");
    if (!f) {
        perror(argv[1]);
        return 1;
    }
    while (fgets(line, sizeof line, f)) {
        char *p = line, *end;
        struct timespec t0, t1;
        for (i = 0; i < AXES; i++) {
            x[i] = strtof(p, &end);
            if (end == p) break;
            p = end;
            while (*p == ',' || *p == ' ' || *p == '\t') p++;
        }
        if (i < AXES) continue;   /* a header or a short line */
        clock_gettime(CLOCK_MONOTONIC, &t0);
        code = API(step)(&st, x, dt, q, w, NULL, NULL);
        clock_gettime(CLOCK_MONOTONIC, &t1);
        if (n == cap) {
            cap = cap ? 2 * cap : 1024;
            times = (double *)realloc(times, cap * sizeof(double));
            if (!times) return 1;
        }
        times[n++] = (t1.tv_sec - t0.tv_sec) * 1e6 + (t1.tv_nsec - t0.tv_nsec) * 1e-3;
        if (code) {
            refused++;
            printf("refused,%d\n", code);
        } else {
            printf("%.9g,%.9g,%.9g,%.9g,%.9g,%.9g,%.9g\n", q[0], q[1], q[2], q[3], w[0], w[1], w[2]);
        }
    }
    fclose(f);
    if (n) {
        qsort(times, n, sizeof(double), cmp);
        fprintf(stderr, "%lu samples, %lu refused, median step time %.3f us, state %lu bytes\n", (unsigned long)n,
                (unsigned long)refused, times[n / 2], (unsigned long)sizeof(st));
    }
    free(times);
    return 0;
}
