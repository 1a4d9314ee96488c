/* A small gyro calibrator in C, for the gyroharness command protocol (docs/score.md).
 *
 *   cc -O2 -o bias_scale bias_scale.c -lm
 *   ./bias_scale fit   PARAMS TABLE.csv [THERMAL.csv]   -> PARAMS: "kx ky kz" (scale per axis)
 *   ./bias_scale apply PARAMS IN.csv OUT.csv
 *
 * fit:   on the rate-table run (columns gyro_*_rad_s, ref_*_rad_s): bias b = per-axis median of
 *        the still samples (|ref| = 0), scale k_i = sum((g_i - b_i) r_i) / sum(r_i^2) over the
 *        turning samples (least squares, gyro = k * table rate + b).
 * apply: power-up bias = per-axis median of the first 2 s of each power-up (column
 *        power_up_index if present), then w = (g - b) / k. Writes t_s and gyro_*_rad_s.
 * Plain C99; reads the DESIGN.md data file ('#' metadata lines, one header line).
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct { int ncol, nrow; char **names; double *v; } table;

static void die(const char *msg, const char *what) {
    fprintf(stderr, "bias_scale: %s%s%s\n", msg, what ? ": " : "", what ? what : "");
    exit(1);
}

static char *copy(const char *s) { /* strdup is POSIX, not C99 */
    char *d = malloc(strlen(s) + 1);
    if (!d) die("out of memory", NULL);
    return strcpy(d, s);
}

static table read_table(const char *path) {
    table t = {0, 0, NULL, NULL};
    FILE *f = fopen(path, "r");
    if (!f) die("cannot open", path);
    size_t cap = 0, len = 0;
    static char line[1 << 16];
    while (fgets(line, sizeof line, f)) {
        if (line[0] == '#') continue;
        line[strcspn(line, "\r\n")] = 0;
        if (!t.names) { /* header */
            for (char *tok = strtok(line, ","); tok; tok = strtok(NULL, ",")) {
                t.names = realloc(t.names, sizeof(char *) * (t.ncol + 1));
                t.names[t.ncol++] = copy(tok);
            }
            continue;
        }
        if (!line[0]) continue;
        if (len + t.ncol > cap) { cap = cap ? 2 * cap : 1 << 16; t.v = realloc(t.v, sizeof(double) * cap); }
        char *p = line, *end;
        for (int c = 0; c < t.ncol; c++) {
            t.v[len + c] = strtod(p, &end);
            if (end == p) die("not a number in", path);
            p = (*end == ',') ? end + 1 : end;
        }
        len += t.ncol;
        t.nrow++;
    }
    fclose(f);
    if (!t.names || t.nrow < 2) die("no samples in", path);
    return t;
}

static int col(const table *t, const char *name, int required) {
    for (int c = 0; c < t->ncol; c++) if (!strcmp(t->names[c], name)) return c;
    if (required) die("missing column", name);
    return -1;
}

static int cmp(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static double median(double *x, int n) {
    qsort(x, n, sizeof(double), cmp);
    return n % 2 ? x[n / 2] : 0.5 * (x[n / 2 - 1] + x[n / 2]);
}

static const char *GYRO[3] = {"gyro_x_rad_s", "gyro_y_rad_s", "gyro_z_rad_s"};
static const char *REF[3] = {"ref_x_rad_s", "ref_y_rad_s", "ref_z_rad_s"};
#define V(t, r, c) ((t).v[(size_t)(r) * (t).ncol + (c)])

static int fit(const char *params, const char *table_path) {
    table t = read_table(table_path);
    int g[3], r[3];
    for (int i = 0; i < 3; i++) { g[i] = col(&t, GYRO[i], 1); r[i] = col(&t, REF[i], 1); }
    double *buf = malloc(sizeof(double) * t.nrow), k[3];
    for (int i = 0; i < 3; i++) {
        int n = 0;
        for (int j = 0; j < t.nrow; j++) {
            double rr = hypot(hypot(V(t, j, r[0]), V(t, j, r[1])), V(t, j, r[2]));
            if (rr == 0.0) buf[n++] = V(t, j, g[i]);
        }
        if (n == 0) die("no still samples in the table run", NULL);
        double b = median(buf, n), sxy = 0, sxx = 0;
        for (int j = 0; j < t.nrow; j++) {
            double x = V(t, j, r[i]);
            sxy += (V(t, j, g[i]) - b) * x;
            sxx += x * x;
        }
        if (sxx == 0) die("the table never turns about an axis", GYRO[i]);
        k[i] = sxy / sxx;
    }
    FILE *f = fopen(params, "w");
    if (!f) die("cannot write", params);
    fprintf(f, "%.17g %.17g %.17g\n", k[0], k[1], k[2]);
    fclose(f);
    return 0;
}

static int apply(const char *params, const char *in, const char *out) {
    double k[3];
    FILE *f = fopen(params, "r");
    if (!f || fscanf(f, "%lf %lf %lf", &k[0], &k[1], &k[2]) != 3) die("cannot read", params);
    fclose(f);
    table t = read_table(in);
    int tc = col(&t, "t_s", 1), pc = col(&t, "power_up_index", 0), g[3];
    for (int i = 0; i < 3; i++) g[i] = col(&t, GYRO[i], 1);
    double rate = (t.nrow - 1) / (V(t, t.nrow - 1, tc) - V(t, 0, tc));
    int nb = (int)(2.0 * rate + 0.5);
    double *w = malloc(sizeof(double) * 3 * t.nrow), *buf = malloc(sizeof(double) * t.nrow);
    for (int a = 0; a < t.nrow;) {
        int z = a + 1;
        while (z < t.nrow && (pc < 0 || V(t, z, pc) == V(t, a, pc))) z++;
        int n = (z - a < nb) ? z - a : nb;
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < n; j++) buf[j] = V(t, a + j, g[i]);
            double b = median(buf, n);
            for (int j = a; j < z; j++) w[3 * j + i] = (V(t, j, g[i]) - b) / k[i];
        }
        a = z;
    }
    f = fopen(out, "w");
    if (!f) die("cannot write", out);
    fprintf(f, "t_s,gyro_x_rad_s,gyro_y_rad_s,gyro_z_rad_s\n");
    for (int j = 0; j < t.nrow; j++)
        fprintf(f, "%.17g,%.17g,%.17g,%.17g\n", V(t, j, tc), w[3 * j], w[3 * j + 1], w[3 * j + 2]);
    fclose(f);
    return 0;
}

int main(int argc, char **argv) {
    if (argc >= 4 && !strcmp(argv[1], "fit")) return fit(argv[2], argv[3]);
    if (argc == 5 && !strcmp(argv[1], "apply")) return apply(argv[2], argv[3], argv[4]);
    fprintf(stderr, "usage: bias_scale fit PARAMS TABLE.csv [THERMAL.csv] | apply PARAMS IN.csv OUT.csv\n");
    return 2;
}
