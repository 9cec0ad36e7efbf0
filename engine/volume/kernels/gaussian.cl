/* OpenCL C kernel on volumes: separable 3-tap Gaussian smoothing (replicated borders), the same arithmetic as
 * gaussian.py's gauss3_axis_kernel (no fused multiply-adds: bit for bit). VOL_T is the source's sample type
 * (built once per type by engine.backend.opencl_backend). Global size (nx, ny, nz): id 0 is x. */
#pragma OPENCL FP_CONTRACT OFF

__kernel void gauss3_axis(__global const VOL_T *src, __global float *dst, const int axis, const float w_side,
                          const float w_centre, const int nz, const int ny, const int nx)
{
    const int x = (int)get_global_id(0);
    const int y = (int)get_global_id(1);
    const int z = (int)get_global_id(2);
    const long plane = (long)ny * nx;
    const long at = z * plane + (long)y * nx + x;
    const float c = (float)src[at];
    float lo = c;
    float hi = c;
    if (axis == 0) {
        lo = (float)src[max(z - 1, 0) * plane + (long)y * nx + x];
        hi = (float)src[min(z + 1, nz - 1) * plane + (long)y * nx + x];
    } else if (axis == 1) {
        lo = (float)src[z * plane + (long)max(y - 1, 0) * nx + x];
        hi = (float)src[z * plane + (long)min(y + 1, ny - 1) * nx + x];
    } else {
        lo = (float)src[at - x + max(x - 1, 0)];
        hi = (float)src[at - x + min(x + 1, nx - 1)];
    }
    const float sum = lo + hi;
    const float side = w_side * sum;
    const float centre = w_centre * c;
    dst[at] = side + centre;
}
