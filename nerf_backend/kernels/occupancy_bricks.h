#ifndef OCCUPANCY_BRICKS_H
#define OCCUPANCY_BRICKS_H
/* The occupancy grids the compiled marches read: bricks of 8³ cells, 64 bytes (a cache line)
 * each (nerf_backend/model_components/occupancy.py's brick_bits). Cell (i, j, k) of a grid of
 * G cells a side is bit k % 8 of byte (i % 8) * 8 + j % 8 of brick
 * ((i / 8) * By + j / 8) * Bz + k / 8, with B = ceil(G / 8). A ray's steps through 8 cells in
 * any direction read one line; in rows of bytes along z a ray along x read a new line (and a
 * new page) at every cell. */

#include <stdint.h>

static inline int brick_bit(const uint8_t *bricks, const int64_t ijk[3], const int64_t cells[3]) {
    const int64_t by = (cells[1] + 7) >> 3, bz = (cells[2] + 7) >> 3;
    const int64_t brick = ((ijk[0] >> 3) * by + (ijk[1] >> 3)) * bz + (ijk[2] >> 3);
    return (bricks[brick * 64 + (ijk[0] & 7) * 8 + (ijk[1] & 7)] >> (ijk[2] & 7)) & 1;
}

#endif
