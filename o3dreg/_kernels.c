/* o3dreg's compiled kernels, called through ctypes (o3dreg/_compiled.py), without the GIL.
 *
 * 1. A bounding volume hierarchy of a mesh's triangles and its exact closest-point query.
 *    Each range of triangles is split in halves at the median of their box centres along their
 *    longest extent, down to leaves of at most `leaf` triangles; a node holds the box of its
 *    triangles, and a node's two children are stored side by side. A query descends the nearer
 *    child first and skips every node whose box is not nearer than the best triangle so far.
 *    The closest point on a triangle is found in the Voronoi region of the point (vertex, edge
 *    or face; Ericson, Real-Time Collision Detection, 5.1.5); flat triangles (a point, a
 *    segment, collinear corners) are answered by their edges.
 * 2. The nearest and second-nearest of a set of sites for many points, on a uniform grid: each
 *    point searches the cells around its own in growing shells and stops once no unsearched
 *    cell can hold a site nearer than its second-nearest.
 * 3. A level's arithmetic: the trilinear field and its gradient at points, the damped normal
 *    equations (block-preconditioned conjugate gradients) and their pair sums, per-triangle
 *    cross products and the open-boundary test. The cross products, the boundary test and the
 *    pair sums keep the numbers of the NumPy/SciPy code they replace (the same operations in
 *    the same order; the tests compare them bit for bit); the conjugate gradients take each
 *    node's 3x3 block as preconditioner where SciPy's took the diagonal.
 *
 * Every query is independent: a query kernel answers the range [begin, end) and the Python side
 * splits one call over threads, so an answer does not depend on the threads (the conjugate
 * gradients and the pair sums run whole on the calling thread). Indices are int64 (the block
 * matrices' int32, as SciPy's), points float64 and finite, arrays C-contiguous; inputs are
 * checked on the Python side (o3dreg/_bvh.py, _nearest.py, _geometry.py,
 * registration/lattice.py, distance.py, _assembly.py, _solvers.py): nothing here reads outside
 * its arrays when they hold what they should. Built without floating-point contraction (see
 * setup.py), so results are the same on every x86-64 machine.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

typedef int64_t idx;
typedef struct {
    double x, y, z;
} vec;

static inline vec sub(vec a, vec b) { return (vec){a.x - b.x, a.y - b.y, a.z - b.z}; }
static inline double dot(vec a, vec b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
static inline vec along(vec a, vec u, double t) { return (vec){a.x + t * u.x, a.y + t * u.y, a.z + t * u.z}; }
static inline double sqdist(vec a, vec b) {
    double dx = a.x - b.x, dy = a.y - b.y, dz = a.z - b.z;
    return dx * dx + dy * dy + dz * dz;
}
static inline double lesser(double a, double b) { return b < a ? b : a; }
static inline double greater(double a, double b) { return b > a ? b : a; }
static inline vec corner(const double *corners, idx t, int k) {
    const double *c = corners + 9 * t + 3 * k;
    return (vec){c[0], c[1], c[2]};
}

/* ---- closest point on a triangle ------------------------------------------------------------ */

/* Closest point to p on the segment ab (the point a when a == b). */
static vec on_segment(vec p, vec a, vec b) {
    vec u = sub(b, a);
    double uu = dot(u, u), t = 0.0;
    if (uu > 0.0) {
        t = dot(sub(p, a), u) / uu;
        t = lesser(1.0, greater(0.0, t));
    }
    return along(a, u, t);
}

/* Closest point to p on a flat triangle abc: the nearest of its edges' closest points. */
static vec on_flat(vec p, vec a, vec b, vec c) {
    vec q = on_segment(p, a, b), r;
    double best = sqdist(q, p), d;
    r = on_segment(p, b, c);
    d = sqdist(r, p);
    if (d < best) {
        q = r;
        best = d;
    }
    r = on_segment(p, c, a);
    d = sqdist(r, p);
    if (d < best) q = r;
    return q;
}

/* Closest point to p on a triangle abc that is not flat, found in its Voronoi region. */
static vec on_triangle(vec p, vec a, vec b, vec c) {
    vec ab = sub(b, a), ac = sub(c, a), ap = sub(p, a);
    double d1 = dot(ab, ap), d2 = dot(ac, ap);
    if (d1 <= 0.0 && d2 <= 0.0) return a;
    vec bp = sub(p, b);
    double d3 = dot(ab, bp), d4 = dot(ac, bp);
    if (d3 >= 0.0 && d4 <= d3) return b;
    double vc = d1 * d4 - d3 * d2;
    if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) return on_segment(p, a, b);
    vec cp = sub(p, c);
    double d5 = dot(ab, cp), d6 = dot(ac, cp);
    if (d6 >= 0.0 && d5 <= d6) return c;
    double vb = d5 * d2 - d1 * d6;
    if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) return on_segment(p, a, c);
    double va = d3 * d6 - d5 * d4;
    if (va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0) return on_segment(p, b, c);
    double denom = va + vb + vc;
    if (!(denom > 0.0)) return on_flat(p, a, b, c); /* flat after all, by rounding */
    double v = vb / denom, w = vc / denom;
    return (vec){a.x + ab.x * v + ac.x * w, a.y + ab.y * v + ac.y * w, a.z + ab.z * v + ac.z * w};
}

static inline vec on(const double *corners, const uint8_t *flat, idx t, vec p) {
    vec a = corner(corners, t, 0), b = corner(corners, t, 1), c = corner(corners, t, 2);
    return flat[t] ? on_flat(p, a, b, c) : on_triangle(p, a, b, c);
}

/* Per triangle, whether it is flat: |ab x ac|^2 <= 1e-20 |ab|^2 |ac|^2 (a point, a segment, or
 * corners collinear to ten digits), where the Voronoi regions of a triangle do not hold. */
static void flat_triangles(const double *corners, idx m, uint8_t *flat) {
    for (idx t = 0; t < m; t++) {
        vec u = sub(corner(corners, t, 1), corner(corners, t, 0));
        vec w = sub(corner(corners, t, 2), corner(corners, t, 0));
        vec n = {u.y * w.z - u.z * w.y, u.z * w.x - u.x * w.z, u.x * w.y - u.y * w.x};
        flat[t] = dot(n, n) <= 1e-20 * dot(u, u) * dot(w, w);
    }
}

/* ---- the tree ------------------------------------------------------------------------------- */

/* Reorder rows s..e-1 of centre (and order alike) so that row k holds the element of rank k - s
 * along axis, none greater before it and none smaller after (Hoare's selection). */
static void select_rank(idx *order, double *centre, int axis, idx s, idx e, idx k) {
    idx lo = s, hi = e - 1;
    while (lo < hi) {
        idx mid = (lo + hi) / 2;
        /* The median of three as the pivot (deterministic; sorted input costs no more). */
        double a = centre[3 * lo + axis], b = centre[3 * mid + axis], c = centre[3 * hi + axis];
        double pivot = greater(lesser(a, b), lesser(greater(a, b), c));
        idx i = lo, j = hi;
        while (i <= j) {
            while (centre[3 * i + axis] < pivot) i++;
            while (centre[3 * j + axis] > pivot) j--;
            if (i <= j) {
                idx o = order[i];
                order[i] = order[j];
                order[j] = o;
                for (int x = 0; x < 3; x++) {
                    double v = centre[3 * i + x];
                    centre[3 * i + x] = centre[3 * j + x];
                    centre[3 * j + x] = v;
                }
                i++;
                j--;
            }
        }
        if (k <= j)
            hi = j;
        else if (k >= i)
            lo = i;
        else
            return;
    }
}

/* The tree of the m triangles `faces` (m x 3) of `vertices`. Outputs, sized by the caller for
 * `capacity` nodes (2 ceil(m / ceil(leaf / 2)) suffice: halving a range longer than a leaf
 * leaves halves of at least (leaf + 1) / 2): order (m; the mesh triangle in each slot of the
 * tree's order), corners (m x 9) and flat (m) in that order, start, stop, left (-1 at a leaf;
 * the right child is left + 1), box (capacity x 6: low corner, high corner). Returns the
 * number of nodes, or -1 when memory is short. */
idx o3dreg_bvh_build(const double *vertices, const idx *faces, idx m, idx leaf, idx capacity,
                     idx *order, double *corners, uint8_t *flat, idx *start, idx *stop, idx *left,
                     double *box) {
    double *tri = malloc(sizeof(double) * 6 * (size_t)(m > 0 ? m : 1));
    double *centre = malloc(sizeof(double) * 3 * (size_t)(m > 0 ? m : 1));
    idx stack[128];
    if (!tri || !centre) {
        free(tri);
        free(centre);
        return -1;
    }
    for (idx t = 0; t < m; t++) {
        const double *p = vertices + 3 * faces[3 * t], *q = vertices + 3 * faces[3 * t + 1];
        const double *r = vertices + 3 * faces[3 * t + 2];
        for (int a = 0; a < 3; a++) {
            tri[6 * t + a] = lesser(lesser(p[a], q[a]), r[a]);
            tri[6 * t + 3 + a] = greater(greater(p[a], q[a]), r[a]);
            centre[3 * t + a] = 0.5 * (tri[6 * t + a] + tri[6 * t + 3 + a]);
        }
        order[t] = t;
    }
    start[0] = 0;
    stop[0] = m;
    left[0] = -1;
    idx count = 1;
    int top = 0;
    stack[0] = 0;
    while (top >= 0) {
        idx node = stack[top--];
        idx s = start[node], e = stop[node];
        if (e - s <= leaf || count + 2 > capacity) continue;
        double lo[3], hi[3];
        for (int a = 0; a < 3; a++) lo[a] = hi[a] = centre[3 * s + a];
        for (idx k = s + 1; k < e; k++)
            for (int a = 0; a < 3; a++) {
                lo[a] = lesser(lo[a], centre[3 * k + a]);
                hi[a] = greater(hi[a], centre[3 * k + a]);
            }
        int axis = 0;
        if (hi[1] - lo[1] > hi[0] - lo[0]) axis = 1;
        if (hi[2] - lo[2] > greater(hi[0] - lo[0], hi[1] - lo[1])) axis = 2;
        idx mid = (s + e) / 2;
        select_rank(order, centre, axis, s, e, mid);
        left[node] = count;
        start[count] = s;
        stop[count] = mid;
        start[count + 1] = mid;
        stop[count + 1] = e;
        left[count] = left[count + 1] = -1;
        stack[++top] = count;
        stack[++top] = count + 1;
        count += 2;
    }
    /* Boxes from the leaves up: children are made after their parent. */
    for (idx node = count - 1; node >= 0; node--) {
        double *b = box + 6 * node;
        if (left[node] < 0) {
            for (int a = 0; a < 3; a++) {
                b[a] = INFINITY;
                b[3 + a] = -INFINITY;
            }
            for (idx k = start[node]; k < stop[node]; k++)
                for (int a = 0; a < 3; a++) {
                    b[a] = lesser(b[a], tri[6 * order[k] + a]);
                    b[3 + a] = greater(b[3 + a], tri[6 * order[k] + 3 + a]);
                }
        } else {
            const double *l = box + 6 * left[node], *r = box + 6 * (left[node] + 1);
            for (int a = 0; a < 3; a++) {
                b[a] = lesser(l[a], r[a]);
                b[3 + a] = greater(l[3 + a], r[3 + a]);
            }
        }
    }
    /* The triangles' corners in the tree's order: a leaf's side by side. */
    for (idx k = 0; k < m; k++)
        for (int c = 0; c < 3; c++)
            memcpy(corners + 9 * k + 3 * c, vertices + 3 * faces[3 * order[k] + c], 3 * sizeof(double));
    flat_triangles(corners, m, flat);
    free(tri);
    free(centre);
    return count;
}

static inline double box_gap(const double *box, idx node, vec p) {
    const double *b = box + 6 * node;
    double gx = greater(greater(b[0] - p.x, 0.0), p.x - b[3]);
    double gy = greater(greater(b[1] - p.y, 0.0), p.y - b[4]);
    double gz = greater(greater(b[2] - p.z, 0.0), p.z - b[5]);
    return gx * gx + gy * gy + gz * gz;
}

/* Closest triangle of points begin..end-1. corners and flat are in the tree's order (slot k
 * holds mesh triangle face_of[k]; rank is its inverse); hint[i] >= 0 names a mesh triangle to
 * start from. Exact ties go to the smaller mesh index among the triangles the search reaches. */
void o3dreg_bvh_query(const double *corners, const uint8_t *flat, const idx *face_of,
                      const idx *rank, const idx *start, const idx *stop, const idx *left,
                      const double *box, const double *points, const idx *hint, double *out_sqr,
                      idx *out_face, double *out_point, idx begin, idx end) {
    idx stack[128];
    double gap[128];
    for (idx i = begin; i < end; i++) {
        vec p = {points[3 * i], points[3 * i + 1], points[3 * i + 2]};
        double best = INFINITY;
        idx found = -1;
        vec q = {0.0, 0.0, 0.0};
        if (hint[i] >= 0) {
            found = rank[hint[i]];
            q = on(corners, flat, found, p);
            best = sqdist(q, p);
        }
        int top = 0;
        stack[0] = 0;
        gap[0] = box_gap(box, 0, p);
        while (top >= 0) {
            idx node = stack[top];
            double near = gap[top--];
            if (near >= best) continue;
            if (left[node] < 0) {
                for (idx k = start[node]; k < stop[node]; k++) {
                    if (k == found) continue;
                    vec r = on(corners, flat, k, p);
                    double d = sqdist(r, p);
                    if (d < best || (found >= 0 && d == best && face_of[k] < face_of[found])) {
                        best = d;
                        found = k;
                        q = r;
                    }
                }
                continue;
            }
            idx a = left[node], b = a + 1;
            double da = box_gap(box, a, p), db = box_gap(box, b, p);
            if (da > db) {
                idx t = a;
                a = b;
                b = t;
                double g = da;
                da = db;
                db = g;
            }
            /* The nearer child is popped first. */
            if (db < best) {
                stack[++top] = b;
                gap[top] = db;
            }
            if (da < best) {
                stack[++top] = a;
                gap[top] = da;
            }
        }
        out_sqr[i] = best;
        out_face[i] = found >= 0 ? face_of[found] : -1;
        out_point[3 * i] = q.x;
        out_point[3 * i + 1] = q.y;
        out_point[3 * i + 2] = q.z;
    }
}

/* ---- nearest two sites on a grid ------------------------------------------------------------ */

/* The cell of coordinate x along one axis of the grid, clamped to [0, dim - 1]. */
static inline idx cell_along(double x, double origin, double size, idx dim) {
    double k = floor((x - origin) / size);
    return k < 0.0 ? 0 : (k > (double)(dim - 1) ? dim - 1 : (idx)k);
}

/* Sites sorted by cell (a counting sort): first (cells + 1 entries, zeroed by the caller) and
 * order, each cell's sites in index order. Returns 0, or -1 when memory is short. */
idx o3dreg_grid_build(const double *sites, idx n, const double *origin, double size,
                      const idx *dims, idx *first, idx *order) {
    idx *cell = malloc(sizeof(idx) * (size_t)(n > 0 ? n : 1));
    idx cells = dims[0] * dims[1] * dims[2];
    if (!cell) return -1;
    for (idx i = 0; i < n; i++) {
        idx c = 0;
        for (int a = 0; a < 3; a++) {
            c = c * dims[a] + cell_along(sites[3 * i + a], origin[a], size, dims[a]);
        }
        cell[i] = c;
        first[c + 1]++;
    }
    for (idx c = 1; c <= cells; c++) first[c] += first[c - 1];
    idx *fill = malloc(sizeof(idx) * (size_t)(cells > 0 ? cells : 1));
    if (!fill) {
        free(cell);
        return -1;
    }
    memcpy(fill, first, sizeof(idx) * (size_t)cells);
    for (idx i = 0; i < n; i++) order[fill[cell[i]]++] = i;
    free(fill);
    free(cell);
    return 0;
}

typedef struct {
    double d1, d2;
    idx i1, i2;
} two;

/* The best two so far, updated with the sites of one cell; lexicographic in (distance, index):
 * exact ties go to the smaller index. */
static inline void visit(const double *sites, const idx *first, const idx *order, idx cell, vec p,
                         two *b) {
    for (idx k = first[cell]; k < first[cell + 1]; k++) {
        idx i = order[k];
        double e0 = sites[3 * i] - p.x, e1 = sites[3 * i + 1] - p.y, e2 = sites[3 * i + 2] - p.z;
        double d = e0 * e0 + e1 * e1 + e2 * e2;
        if (d < b->d1 || (d == b->d1 && i < b->i1)) {
            b->d2 = b->d1;
            b->i2 = b->i1;
            b->d1 = d;
            b->i1 = i;
        } else if (d < b->d2 || (d == b->d2 && i < b->i2)) {
            b->d2 = d;
            b->i2 = i;
        }
    }
}

/* Distance from p to the grid's cells outside [c - r, c + r] on one axis (inf if none). */
static inline double side_gap(double p, double origin, double size, idx dim, idx c, idx r) {
    double g = INFINITY;
    if (c - r > 0) g = greater(p - (origin + (double)(c - r) * size), 0.0);
    if (c + r < dim - 1) g = lesser(g, greater(origin + (double)(c + r + 1) * size - p, 0.0));
    return g;
}

/* The nearest and second-nearest site of p on the grid. */
static two search_two(const double *sites, const idx *first, const idx *order, const double *origin,
                      double size, const idx *dims, const double *p3) {
    vec p = {p3[0], p3[1], p3[2]};
    idx c[3];
    double away[3]; /* distance from the point to the grid's extent, per axis */
    for (int a = 0; a < 3; a++) {
        c[a] = cell_along(p3[a], origin[a], size, dims[a]);
        double top = origin[a] + (double)dims[a] * size;
        away[a] = greater(greater(origin[a] - p3[a], 0.0), p3[a] - top);
    }
    two b = {INFINITY, INFINITY, -1, -1};
    for (idx r = 0;; r++) {
        /* The shell of cells at Chebyshev distance r from the point's cell. */
        idx x0 = c[0] - r < 0 ? 0 : c[0] - r, x1 = c[0] + r > dims[0] - 1 ? dims[0] - 1 : c[0] + r;
        idx y0 = c[1] - r < 0 ? 0 : c[1] - r, y1 = c[1] + r > dims[1] - 1 ? dims[1] - 1 : c[1] + r;
        idx z0 = c[2] - r < 0 ? 0 : c[2] - r, z1 = c[2] + r > dims[2] - 1 ? dims[2] - 1 : c[2] + r;
        for (idx x = x0; x <= x1; x++)
            for (idx y = y0; y <= y1; y++) {
                idx row = (x * dims[1] + y) * dims[2];
                if (llabs(x - c[0]) == r || llabs(y - c[1]) == r) {
                    for (idx z = z0; z <= z1; z++) visit(sites, first, order, row + z, p, &b);
                } else { /* inside the shell's x-y extent: only its two z faces */
                    if (c[2] - r >= 0) visit(sites, first, order, row + c[2] - r, p, &b);
                    if (c[2] + r < dims[2]) visit(sites, first, order, row + c[2] + r, p, &b);
                }
            }
        /* The nearest unsearched cell lies outside the block [c - r, c + r] on some axis: its
         * squared distance is at least the gap to that side plus the point's distance to the
         * grid's extent along the other two axes. */
        double bound = INFINITY;
        for (int a = 0; a < 3; a++) {
            double g = side_gap(p3[a], origin[a], size, dims[a], c[a], r);
            double rest = 0.0;
            for (int o = 0; o < 3; o++)
                if (o != a) rest += away[o] * away[o];
            bound = lesser(bound, g * g + rest);
        }
        if (b.d2 < bound || bound == INFINITY) return b;
    }
}

/* Nearest and second-nearest site of points begin..end-1: out_d (k x 2) distances, out_i (k x 2)
 * indices (inf and -1 for a missing second). */
void o3dreg_grid_nearest_two(const double *sites, const idx *first, const idx *order,
                             const double *origin, double size, const idx *dims,
                             const double *points, double *out_d, idx *out_i, idx begin, idx end) {
    for (idx j = begin; j < end; j++) {
        two b = search_two(sites, first, order, origin, size, dims, points + 3 * j);
        out_d[2 * j] = sqrt(b.d1);
        out_d[2 * j + 1] = sqrt(b.d2);
        out_i[2 * j] = b.i1;
        out_i[2 * j + 1] = b.i2;
    }
}

/* The barycentre term's assignment, kept up to date (o3dreg.registration._terms.BarycentreTerm):
 * point j is searched again (all of them when `all` is set) unless its nearest site is still
 * provably nearest, own + (moved - mark[j]) < gap[j] with own = path[nearest[j]] - path_mark[j];
 * a search sets nearest[j], gap[j] (second minus first distance), mark[j] = moved and
 * path_mark[j] = path[nearest[j]]. distance[j]: the distance to the nearest site. */
void o3dreg_grid_reassign(const double *sites, const idx *first, const idx *order,
                          const double *origin, double size, const idx *dims,
                          const double *points, const double *path, double moved, int all,
                          idx *nearest, double *gap, double *mark, double *path_mark,
                          double *distance, idx begin, idx end) {
    for (idx j = begin; j < end; j++) {
        if (all || path[nearest[j]] - path_mark[j] + (moved - mark[j]) >= gap[j]) {
            two b = search_two(sites, first, order, origin, size, dims, points + 3 * j);
            nearest[j] = b.i1;
            gap[j] = sqrt(b.d2) - sqrt(b.d1);
            mark[j] = moved;
            path_mark[j] = path[b.i1];
        }
        const double *p = points + 3 * j, *q = sites + 3 * nearest[j];
        double e0 = p[0] - q[0], e1 = p[1] - q[1], e2 = p[2] - q[2];
        distance[j] = sqrt(e0 * e0 + e1 * e1 + e2 * e2);
    }
}

/* ---- trilinear lattices --------------------------------------------------------------------- */

/* The cell of point p and the factors of its 8 corners' trilinear weights and their derivatives
 * (o3dreg.registration.lattice.TrilinearLattice.basis): f[bit][axis] the weight factors,
 * df[bit][axis] their derivatives (zero along an axis where p lies outside the box, which the
 * field is clamped to). Returns the cell's first node. */
static idx trilinear(const double *origin, const double *cell, const idx *shape, const double *p,
                     double f[2][3], double df[2][3]) {
    idx c[3];
    for (int a = 0; a < 3; a++) {
        double s = (p[a] - origin[a]) / cell[a];
        double top = (double)shape[a];
        int inside = s >= 0.0 && s <= top;
        s = s >= 0.0 ? (s <= top ? s : top) : 0.0; /* NaN (a non-finite box) to 0 */
        double k = floor(s);
        c[a] = k > (double)(shape[a] - 1) ? shape[a] - 1 : (idx)k;
        double t = s - (double)c[a];
        f[0][a] = 1.0 - t;
        f[1][a] = t;
        df[0][a] = inside ? -1.0 / cell[a] : 0.0;
        df[1][a] = inside ? 1.0 / cell[a] : 0.0;
    }
    return (c[0] * (shape[1] + 1) + c[1]) * (shape[2] + 1) + c[2];
}

/* Adds the displacement of the lattice (node displacements `field`, (nodes x 3)) at points
 * begin..end-1 to out (k x 3); with `gradient`, adds its spatial derivative to out (k x 3 x 3,
 * [c][a] = d u_c / d x_a) instead. */
void o3dreg_lattice_field(const double *origin, const double *cell, const idx *shape,
                          const double *field, const double *points, int gradient, double *out,
                          idx begin, idx end) {
    idx ny1 = shape[1] + 1, nz1 = shape[2] + 1;
    for (idx i = begin; i < end; i++) {
        double f[2][3], df[2][3];
        idx first = trilinear(origin, cell, shape, points + 3 * i, f, df);
        double sum[9] = {0.0};
        for (int k = 0; k < 8; k++) {
            int b0 = k >> 2, b1 = (k >> 1) & 1, b2 = k & 1;
            const double *d = field + 3 * (first + (b0 * ny1 + b1) * nz1 + b2);
            if (gradient) {
                double g[3] = {df[b0][0] * f[b1][1] * f[b2][2], f[b0][0] * df[b1][1] * f[b2][2],
                               f[b0][0] * f[b1][1] * df[b2][2]};
                for (int c = 0; c < 3; c++)
                    for (int a = 0; a < 3; a++) sum[3 * c + a] += d[c] * g[a];
            } else {
                double w = f[b0][0] * f[b1][1] * f[b2][2];
                for (int c = 0; c < 3; c++) sum[c] += w * d[c];
            }
        }
        int count = gradient ? 9 : 3;
        for (int e = 0; e < count; e++) out[count * i + e] += sum[e];
    }
}

/* ---- damped normal equations by conjugate gradients ----------------------------------------- */

static double dot_n(const double *a, const double *b, idx n) {
    double s = 0.0;
    for (idx i = 0; i < n; i++) s += a[i] * b[i];
    return s;
}

/* y = (A + diag(damping)) x for A in 3x3-block CSR form (indptr, indices, blocks row-major). */
static void damped_product(idx nb, const int32_t *indptr, const int32_t *indices,
                           const double *blocks, const double *damping, const double *x,
                           double *y) {
    for (idx r = 0; r < nb; r++) {
        double s0 = damping[3 * r] * x[3 * r], s1 = damping[3 * r + 1] * x[3 * r + 1],
               s2 = damping[3 * r + 2] * x[3 * r + 2];
        for (idx k = indptr[r]; k < indptr[r + 1]; k++) {
            const double *m = blocks + 9 * k, *v = x + 3 * (idx)indices[k];
            s0 += m[0] * v[0] + m[1] * v[1] + m[2] * v[2];
            s1 += m[3] * v[0] + m[4] * v[1] + m[5] * v[2];
            s2 += m[6] * v[0] + m[7] * v[1] + m[8] * v[2];
        }
        y[3 * r] = s0;
        y[3 * r + 1] = s1;
        y[3 * r + 2] = s2;
    }
}

/* The Cholesky factor (l00, l10, l11, l20, l21, l22) of a symmetric 3x3 block, or of its
 * diagonal where the block is not positive definite. */
static void block_factor(const double *m, const double *damping, double *l) {
    double a00 = m[0] + damping[0], a11 = m[4] + damping[1], a22 = m[8] + damping[2];
    double a10 = m[3], a20 = m[6], a21 = m[7];
    double l00 = a00 > 0.0 ? sqrt(a00) : 0.0;
    double l10 = l00 > 0.0 ? a10 / l00 : 0.0, l20 = l00 > 0.0 ? a20 / l00 : 0.0;
    double p11 = a11 - l10 * l10;
    double l11 = p11 > 0.0 ? sqrt(p11) : 0.0;
    double l21 = l11 > 0.0 ? (a21 - l20 * l10) / l11 : 0.0;
    double p22 = a22 - l20 * l20 - l21 * l21;
    double l22 = p22 > 0.0 ? sqrt(p22) : 0.0;
    if (l00 > 0.0 && l11 > 0.0 && l22 > 0.0 && isfinite(l21) && isfinite(l22)) {
        double out[6] = {l00, l10, l11, l20, l21, l22};
        memcpy(l, out, sizeof out);
        return;
    }
    double out[6] = {a00 > 0.0 ? sqrt(a00) : 1.0, 0.0, a11 > 0.0 ? sqrt(a11) : 1.0,
                     0.0, 0.0, a22 > 0.0 ? sqrt(a22) : 1.0};
    memcpy(l, out, sizeof out);
}

/* z = L^-T L^-1 r for one block's factor. */
static inline void block_apply(const double *l, const double *r, double *z) {
    double y0 = r[0] / l[0];
    double y1 = (r[1] - l[1] * y0) / l[2];
    double y2 = (r[2] - l[3] * y0 - l[4] * y1) / l[5];
    z[2] = y2 / l[5];
    z[1] = (y1 - l[4] * z[2]) / l[2];
    z[0] = (y0 - l[1] * z[1] - l[3] * z[2]) / l[0];
}

/* Solves (A + diag(damping)) x = b (A symmetric positive semidefinite, 3x3-block CSR; each row's
 * blocks include its diagonal block) by conjugate gradients preconditioned by the inverse of
 * each 3x3 diagonal block, from x = 0, until |r| <= rtol |b|. Returns the iterations, -1 when
 * maxiter iterations do not reach the tolerance (or the iteration breaks down), -2 when memory
 * is short. */
idx o3dreg_damped_cg(idx nb, const int32_t *indptr, const int32_t *indices, const double *blocks,
                     const double *damping, const double *b, double rtol, idx maxiter, double *x) {
    idx n = 3 * nb;
    double *work = malloc(sizeof(double) * (size_t)(4 * n + 6 * nb + 1));
    if (!work) return -2;
    double *r = work, *z = r + n, *p = z + n, *q = p + n, *factor = q + n;
    for (idx row = 0; row < nb; row++) {
        const double *diagonal = NULL;
        for (idx k = indptr[row]; k < indptr[row + 1]; k++)
            if (indices[k] == row) diagonal = blocks + 9 * k;
        double zero[9] = {0.0};
        block_factor(diagonal ? diagonal : zero, damping + 3 * row, factor + 6 * row);
    }
    for (idx i = 0; i < n; i++) {
        x[i] = 0.0;
        r[i] = b[i];
    }
    double bound = rtol * sqrt(dot_n(b, b, n));
    idx result = -1;
    if (sqrt(dot_n(r, r, n)) <= bound) {
        result = 0;
    } else {
        for (idx row = 0; row < nb; row++) block_apply(factor + 6 * row, r + 3 * row, z + 3 * row);
        memcpy(p, z, sizeof(double) * (size_t)n);
        double rho = dot_n(r, z, n);
        for (idx it = 1; it <= maxiter; it++) {
            damped_product(nb, indptr, indices, blocks, damping, p, q);
            double pq = dot_n(p, q, n);
            if (!(pq > 0.0) || !isfinite(rho)) break;
            double alpha = rho / pq;
            for (idx i = 0; i < n; i++) {
                x[i] += alpha * p[i];
                r[i] -= alpha * q[i];
            }
            if (sqrt(dot_n(r, r, n)) <= bound) {
                result = it;
                break;
            }
            for (idx row = 0; row < nb; row++)
                block_apply(factor + 6 * row, r + 3 * row, z + 3 * row);
            double next = dot_n(r, z, n);
            double beta = next / rho;
            rho = next;
            for (idx i = 0; i < n; i++) p[i] = z[i] + beta * p[i];
        }
    }
    free(work);
    return result;
}

/* ---- per-triangle measures and the open boundary ------------------------------------------- */

/* (b - a) x (c - a) of triangle t, with NumPy's operations in NumPy's order
 * (o3dreg._geometry.face_cross). */
static inline vec face_cross_of(const double *vertices, const idx *faces, idx t) {
    const double *a = vertices + 3 * faces[3 * t], *b = vertices + 3 * faces[3 * t + 1],
                 *c = vertices + 3 * faces[3 * t + 2];
    double b0 = b[0] - a[0], b1 = b[1] - a[1], b2 = b[2] - a[2];
    double c0 = c[0] - a[0], c1 = c[1] - a[1], c2 = c[2] - a[2];
    return (vec){b1 * c2 - b2 * c1, b2 * c0 - b0 * c2, b0 * c1 - b1 * c0};
}

static inline double norm_of(vec v) { return sqrt(v.x * v.x + v.y * v.y + v.z * v.z); }

/* Triangles begin..end-1: their cross products (out, m x 3), or with `areas` the cross
 * products' lengths (out, m): twice their areas. */
void o3dreg_face_cross(const double *vertices, const idx *faces, int areas, double *out,
                       idx begin, idx end) {
    for (idx t = begin; t < end; t++) {
        vec n = face_cross_of(vertices, faces, t);
        if (areas) {
            out[t] = norm_of(n);
        } else {
            out[3 * t] = n.x;
            out[3 * t + 1] = n.y;
            out[3 * t + 2] = n.z;
        }
    }
}

/* Whether points begin..end-1 lie beyond the surface's open boundary
 * (o3dreg.registration.distance.SurfaceDistanceQuery.beyond_boundary): the closest point
 * (closest, on triangle face) has a barycentric coordinate <= 1e-9 opposite an open edge, or two
 * such coordinates at a boundary vertex, and the offset's part tangent to the triangle is longer
 * than `reach`. Per triangle: open_edge (m x 3), touches (whether it touches the boundary); per
 * vertex: on_boundary. The barycentric coordinates are o3dreg._geometry.barycentric's. */
void o3dreg_beyond_boundary(const double *vertices, const idx *faces, const uint8_t *open_edge,
                            const uint8_t *touches, const uint8_t *on_boundary,
                            const double *points, const idx *face, const double *closest,
                            double reach, uint8_t *out, idx begin, idx end) {
    for (idx i = begin; i < end; i++) {
        idx t = face[i];
        out[i] = 0;
        if (!touches[t]) continue;
        const idx *corner = faces + 3 * t;
        vec a = {vertices[3 * corner[0]], vertices[3 * corner[0] + 1], vertices[3 * corner[0] + 2]};
        vec b = {vertices[3 * corner[1]], vertices[3 * corner[1] + 1], vertices[3 * corner[1] + 2]};
        vec c = {vertices[3 * corner[2]], vertices[3 * corner[2] + 1], vertices[3 * corner[2] + 2]};
        vec q = {closest[3 * i], closest[3 * i + 1], closest[3 * i + 2]};
        vec v0 = sub(b, a), v1 = sub(c, a), v2 = sub(q, a);
        double d00 = dot(v0, v0), d01 = dot(v0, v1), d11 = dot(v1, v1);
        double d20 = dot(v2, v0), d21 = dot(v2, v1);
        double denom = d00 * d11 - d01 * d01;
        if (denom == 0.0) denom = 1.0;
        double v = (d11 * d20 - d01 * d21) / denom, w = (d00 * d21 - d01 * d20) / denom;
        double bary[3] = {1.0 - v - w, v, w}, total;
        for (int k = 0; k < 3; k++) bary[k] = bary[k] < 0.0 ? 0.0 : bary[k];
        total = bary[0] + bary[1] + bary[2];
        int hit = 0, tiny = 0, top = 0;
        for (int k = 0; k < 3; k++) {
            bary[k] /= total;
            if (bary[k] <= 1e-9) {
                tiny++;
                hit |= open_edge[3 * t + k];
            }
            if (bary[k] > bary[top]) top = k;
        }
        if (tiny >= 2) hit |= on_boundary[corner[top]]; /* at a corner: that vertex */
        if (!hit) continue;
        vec n = face_cross_of(vertices, faces, t);
        double length = norm_of(n);
        if (!(length > 0.0)) length = 1.0;
        n = (vec){n.x / length, n.y / length, n.z / length};
        vec diff = sub((vec){points[3 * i], points[3 * i + 1], points[3 * i + 2]}, q);
        double along_normal = dot(diff, n);
        vec tangent = sub(diff, (vec){along_normal * n.x, along_normal * n.y, along_normal * n.z});
        out[i] = norm_of(tangent) > reach;
    }
}

/* ---- the normal equations' pair sums -------------------------------------------------------- */

/* S @ metric (columns values per point) for S given by its transpose in row-compressed form
 * (points x pairs: indptr, slot, factor), only its pairs (a, b) with a <= b stored: their sums
 * go to half (pairs x columns, zeroed by the caller), each pair's points summed in point order
 * (as SciPy's product with the column-compressed S), and every pair's row of out is then that of
 * its mirror (b, a) -> (a, b) (the same products: W_ia W_ib = W_ib W_ia). */
void o3dreg_pair_sums(idx points, const int64_t *indptr, const int32_t *slot,
                      const double *factor, const double *metric, idx columns, idx pairs,
                      const int64_t *mirror, double *half, double *out) {
    for (idx i = 0; i < points; i++) {
        const double *m = metric + columns * i;
        if (columns == 6) { /* the metrics' 6 entries, held in registers */
            double m0 = m[0], m1 = m[1], m2 = m[2], m3 = m[3], m4 = m[4], m5 = m[5];
            for (idx k = indptr[i]; k < indptr[i + 1]; k++) {
                double f = factor[k], *o = half + 6 * (idx)slot[k];
                o[0] += f * m0;
                o[1] += f * m1;
                o[2] += f * m2;
                o[3] += f * m3;
                o[4] += f * m4;
                o[5] += f * m5;
            }
            continue;
        }
        for (idx k = indptr[i]; k < indptr[i + 1]; k++) {
            double *o = half + columns * (idx)slot[k];
            for (idx c = 0; c < columns; c++) o[c] += factor[k] * m[c];
        }
    }
    for (idx p = 0; p < pairs; p++)
        memcpy(out + columns * p, half + columns * mirror[p], sizeof(double) * (size_t)columns);
}

/* ---- binary PLY face records ------------------------------------------------------------- */

/* Walk `faces` records of a binary PLY list property: a count of `count_size` bytes (1, 2 or 4;
 * signed when `count_signed`) followed by that many indices of `index_size` bytes, in `nbytes`
 * of data. Returns the bytes walked, or -(k + 1) when record k's count is below 3 (Open3D's
 * reader crashes on a polygon of fewer corners) or the record runs past the data. */
idx o3dreg_ply_walk(const uint8_t *data, idx nbytes, idx faces, int count_size, int count_signed,
                    int big_endian, int index_size) {
    idx at = 0;
    for (idx k = 0; k < faces; k++) {
        if (at + count_size > nbytes) return -(k + 1);
        uint64_t raw = 0;
        for (int b = 0; b < count_size; b++) {
            int shift = 8 * (big_endian ? count_size - 1 - b : b);
            raw |= (uint64_t)data[at + b] << shift;
        }
        int64_t count = (int64_t)raw;
        if (count_signed && (raw >> (8 * count_size - 1)) & 1) count -= (int64_t)1 << (8 * count_size);
        if (count < 3) return -(k + 1);
        at += count_size + count * index_size;
        if (at > nbytes) return -(k + 1);
    }
    return at;
}

/* The library is loaded with ctypes, not imported; this stub only satisfies build tools that
 * expect an extension module's entry point. */
void *PyInit__kernels(void) { return NULL; }
