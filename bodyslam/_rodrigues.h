/* Rodrigues for the compiled loops (bodyslam/vision/_tube_fit.c, bodyslam/fusion/_ekf_rss.c): a rotation vector
   rv (3,) -> its matrix R (3x3, row-major), with the series below 1e-4 rad, as bodyslam.geometry.rotvec_to_matrix. */
#ifndef BODYSLAM_RODRIGUES_H
#define BODYSLAM_RODRIGUES_H
#include <math.h>

static void rodrigues(const double *rv, double R[9]) {
    double x = rv[0], y = rv[1], z = rv[2];
    double t2 = x * x + y * y + z * z, th = sqrt(t2), a, b;
    if (th < 1e-4) {
        a = 1.0 - t2 / 6.0;
        b = 0.5 - t2 / 24.0;
    } else {
        a = sin(th) / th;
        b = (1.0 - cos(th)) / t2;
    }
    R[0] = 1.0 - b * (y * y + z * z);
    R[1] = -a * z + b * x * y;
    R[2] = a * y + b * x * z;
    R[3] = a * z + b * x * y;
    R[4] = 1.0 - b * (x * x + z * z);
    R[5] = -a * x + b * y * z;
    R[6] = -a * y + b * x * z;
    R[7] = a * x + b * y * z;
    R[8] = 1.0 - b * (x * x + y * y);
}

#endif
