/* rosbag2's ``messages`` table decoded straight from the SQLite file's B-tree pages, in C.
 *
 * The same decoder as the numpy one in sqlitepages.py (which stays as the fallback when this
 * module is not built, and as an independent implementation the tests compare against), one
 * pass per cell instead of ~20 whole-array passes. File format:
 * https://www.sqlite.org/fileformat2.html. The file is untrusted input: every read is bounded
 * by the page it belongs to, every page is visited at most once, and any inconsistency raises
 * ``Malformed`` (the caller then reads the table through SQL instead).
 *
 *   decode(buf, root, page_size, usable, topic, time, size, release, release_step) -> n
 *       Walks the table B-tree under page ``root`` in rowid order and writes, per row, the
 *       topic id, the timestamp and the data blob's length into the int64 buffers (their
 *       length is the row count the caller expects; more cells than that is an error).
 *       Calls ``release(start, end)`` (byte offsets) after every ``release_step`` bytes of
 *       pages it has read, so the caller can unmap them. The GIL is released meanwhile.
 *
 *   decode_heads(buf, root, page_size, usable, topic, time, size, release, release_step,
 *                want, heads, rows) -> (n, m)
 *       decode(), and for every row whose topic id is in ``want`` (int64) the first
 *       ``len(heads) / len(rows)`` bytes of its data blob (zero-filled when the blob is
 *       shorter) into the next row of ``heads`` (uint8) and the row's number into ``rows``
 *       (int64, as long as the outputs): m such rows. ``Malformed`` when such a blob's first
 *       bytes are not on its leaf page (an overflowing blob with a tiny local part).
 *
 *   group(tids, times, sizes, ids, counts, nbytes, out_times) -> bool
 *       Stable counting sort of ``times`` by topic id: out_times holds the times of ids[0],
 *       then ids[1], ...; counts/nbytes per id. False (nothing to rely on) when a row has an
 *       id not in ``ids`` or the ids span too wide a range for a lookup table.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

static PyObject *Malformed;

typedef struct {
    const uint8_t *buf;
    uint64_t page_size, usable, n_pages;
    int64_t *topic, *time, *size;
    Py_ssize_t cap, n;
    const char *err;
    uint64_t lo, hi; /* byte range read since the last release */
    uint8_t *seen;   /* bitmap of the pages visited or queued */
    uint32_t *stack; /* pages still to visit, the next one last */
    uint64_t depth, room; /* entries on the stack, and its capacity */
    int nomem;
    const int64_t *want; /* decode_heads: topic ids whose blob heads to copy (nwant of them) */
    Py_ssize_t nwant, m; /* ... and the rows copied so far */
    uint8_t *heads;      /* m x head rows */
    int64_t *rows;
    uint64_t head;
} Walk;

/* decode_heads: the first w->head bytes of the data blob of row w->n - 1 (topic ``tid``, blob
 * of ``dsize`` bytes starting at ``data``, ``avail`` of them on the page), when ``tid`` is
 * wanted. 0 on success, else w->err is set. */
static inline int blob_head(Walk *w, int64_t tid, const uint8_t *data, uint64_t dsize, uint64_t avail) {
    Py_ssize_t j = 0;
    while (j < w->nwant && w->want[j] != tid) j++;
    if (j == w->nwant) return 0;
    uint64_t k = dsize < w->head ? dsize : w->head;
    if (avail < k) return (w->err = "a blob's first bytes are not on its leaf page", -1);
    uint8_t *out = w->heads + (uint64_t)w->m * w->head;
    if (k == 12) { /* the usual head (CDR encapsulation + stamp): a fixed-size copy */
        memcpy(out, data, 12);
    } else {
        memcpy(out, data, k);
        if (k < w->head) memset(out + k, 0, w->head - k);
    }
    w->rows[w->m++] = w->n - 1;
    return 0;
}

/* A varint of at most 9 bytes at p: its length, 0 if it runs to ``end`` or past it. With
 * ``checked`` 0 the caller guarantees 9 readable bytes at p and ``end`` is only the limit the
 * varint must end before (the compiler drops the per-byte bound checks). */
static inline __attribute__((always_inline)) int varint(const uint8_t *p, const uint8_t *end, uint64_t *out,
                                                        int checked) {
    if ((!checked || p < end) && !(p[0] & 0x80)) { /* the common case: one byte */
        *out = p[0];
        return p + 1 <= end ? 1 : 0;
    }
    uint64_t v = 0;
    for (int i = 0; i < 8; i++) {
        if (checked && p + i >= end) return 0;
        uint8_t b = p[i];
        v = (v << 7) | (b & 0x7f);
        if (!(b & 0x80)) {
            *out = v;
            return p + i + 1 <= end ? i + 1 : 0;
        }
    }
    if (checked && p + 8 >= end) return 0;
    *out = (v << 8) | p[8];
    return p + 9 <= end ? 9 : 0;
}

/* Width in bytes of an integer serial type (1-6, 8, 9); -1 for anything else. */
static inline int int_width(uint64_t t) {
    static const int w[10] = {-1, 1, 2, 3, 4, 6, 8, -1, 0, 0};
    return t < 10 ? w[t] : -1;
}

/* Big-endian two's complement integer of serial type t (int_width(t) >= 0) at p. */
static inline int64_t int_value(uint64_t t, const uint8_t *p) {
    uint64_t v;
    switch (t) {
    case 1: return (int8_t)p[0];
    case 2: return (int16_t)((uint16_t)p[0] << 8 | p[1]);
    case 3: v = (uint64_t)p[0] << 16 | (uint64_t)p[1] << 8 | p[2]; return (int64_t)(v ^ 0x800000) - 0x800000;
    case 4: return (int32_t)((uint32_t)p[0] << 24 | (uint32_t)p[1] << 16 | (uint32_t)p[2] << 8 | p[3]);
    case 5:
        v = 0;
        for (int i = 0; i < 6; i++) v = (v << 8) | p[i];
        return (int64_t)(v ^ 0x800000000000) - 0x800000000000;
    case 6:
        memcpy(&v, p, 8);
        return (int64_t)__builtin_bswap64(v);
    case 9: return 1;
    default: return 0; /* 8 */
    }
}

static inline uint64_t be16(const uint8_t *p) { return (uint64_t)p[0] << 8 | p[1]; }
static inline uint64_t be32(const uint8_t *p) {
    return (uint64_t)p[0] << 24 | (uint64_t)p[1] << 16 | (uint64_t)p[2] << 8 | p[3];
}

static inline void touched(Walk *w, uint64_t off) {
    if (off < w->lo) w->lo = off;
    if (off + w->page_size > w->hi) w->hi = off + w->page_size;
}

#define FAIL(msg) return (w->err = (msg), -1)
#define NOT4 "records are not 4 columns (id, topic_id, timestamp, data)"
#define FAR 96 /* a cell this far from its page's end is decoded without per-byte bound checks */

/* One leaf cell at p: its row appended to the outputs. 0 on success, else w->err is set.
 * ``checked`` 0: the caller guarantees FAR readable bytes at p, which covers every byte read
 * here (at most 9 + 9 + 9 + 4 * 9 + 8 + 8 = 79). */
static inline __attribute__((always_inline)) int cell(Walk *w, const uint8_t *p, const uint8_t *end,
                                                      int checked) {
    const uint64_t usable = w->usable;
    /* payload kept on the page: https://www.sqlite.org/fileformat2.html#b_tree_pages */
    const uint64_t max_local = usable - 35, min_local = (usable - 12) * 32 / 255 - 23;
    uint64_t payload, rowid, hsize, t0, t1, t2, t3;
    int k = varint(p, end, &payload, checked);
    if (!k) FAIL("leaf cell outside its page");
    p += k;
    k = varint(p, end, &rowid, checked);
    if (!k) FAIL("leaf cell outside its page");
    p += k;
    uint64_t local = payload, room = (uint64_t)(end - p);
    if (payload > max_local) {
        uint64_t kk = min_local + (payload - min_local) % (usable - 4);
        local = kk <= max_local ? kk : min_local;
        if (room < 4) FAIL("record outside its page");
        room -= 4; /* the first overflow page's number follows the local part */
    }
    if (local > room) FAIL("record outside its page");
    const uint8_t *rec = p, *rend = p + local;
    k = varint(p, rend, &hsize, checked);
    if (!k || hsize > local) FAIL("record header outside its page");
    p += k;
    const uint8_t *hend = rec + hsize;
    if (!(k = varint(p, hend, &t0, checked))) FAIL(NOT4);
    p += k;
    if (!(k = varint(p, hend, &t1, checked))) FAIL(NOT4);
    p += k;
    if (!(k = varint(p, hend, &t2, checked))) FAIL(NOT4);
    p += k;
    if (!(k = varint(p, hend, &t3, checked))) FAIL(NOT4);
    if (p + k != hend) FAIL(NOT4);
    int wt = int_width(t1), wts = int_width(t2);
    if (t0 != 0 || wt < 0 || wts < 0 || t3 < 12 || (t3 & 1)) FAIL("unexpected column types in the messages table");
    if (hsize + (uint64_t)(wt + wts) > local) FAIL("record values outside their page");
    uint64_t dsize = (t3 - 12) / 2;
    if (payload != hsize + (uint64_t)(wt + wts) + dsize) FAIL("payload size disagrees with the record");
    w->topic[w->n] = int_value(t1, hend);
    w->time[w->n] = int_value(t2, hend + wt);
    w->size[w->n] = (int64_t)dsize;
    w->n++;
    if (w->nwant) {
        const uint8_t *data = hend + wt + wts;
        return blob_head(w, w->topic[w->n - 1], data, dsize, (uint64_t)(rend - data));
    }
    return 0;
}

/* Integer width per serial type byte (-1: not an integer type), for the fast path. */
static int8_t WIDTH[256];

/* Cells of one leaf page (flag already checked). 0 on success, else w->err is set.
 *
 * Fast path: a cell at least FAR bytes before the page's end whose payload size takes at most
 * two bytes, stored wholly on the page, with a one-byte header size, one-byte serial types
 * for id/topic_id/timestamp and a one- or two-byte blob type: every varint boundary is then
 * known from a few byte tests, and each check of :func:`cell` holds by construction or is made
 * here. Anything else (or any failed check) goes through :func:`cell`, which raises the error. */
static int leaf(Walk *w, const uint8_t *page) {
    const uint64_t usable = w->usable;
    const uint8_t *end = page + usable;
    uint64_t ncells = be16(page + 3);
    if (8 + 2 * ncells > usable) FAIL("leaf cell count out of range");
    if ((uint64_t)(w->cap - w->n) < ncells) FAIL("more cells in the messages B-tree than count(*) says");
    const uint64_t max_local = usable - 35;
    int64_t *topic = w->topic, *time = w->time, *size = w->size;
    Py_ssize_t n = w->n;
    for (uint64_t i = 0; i < ncells; i++) {
        uint64_t ptr = be16(page + 8 + 2 * i);
        if (ptr < 8 + 2 * ncells || ptr >= usable) FAIL("leaf cell outside its page");
        const uint8_t *p = page + ptr;
        if (ptr + FAR <= usable) {
            uint64_t payload, word, t3;
            if (p[0] < 0x80) {
                payload = p[0];
                p += 1;
            } else if (p[1] < 0x80) {
                payload = (uint64_t)(p[0] & 0x7f) << 7 | p[1];
                p += 2;
            } else {
                goto general;
            }
            memcpy(&word, p, 8); /* the rowid: skipped, its length from the continuation bits */
            uint64_t stops = ~word & 0x8080808080808080ULL;
            if (!stops) goto general;
            p += (__builtin_ctzll(stops) >> 3) + 1;
            unsigned hsize = p[0], t1 = p[2], t2 = p[3];
            if (((hsize | t1 | t2) & 0x80) || p[1] != 0) goto general;
            if (p[4] < 0x80) {
                t3 = p[4];
                if (hsize != 5) goto general;
            } else if (p[5] < 0x80) {
                t3 = (uint64_t)(p[4] & 0x7f) << 7 | p[5];
                if (hsize != 6) goto general;
            } else {
                goto general;
            }
            int wt = WIDTH[t1], wts = WIDTH[t2];
            if ((wt | wts) < 0 || t3 < 12 || (t3 & 1)) goto general;
            uint64_t dsize = (t3 - 12) >> 1;
            if (payload > max_local || payload > (uint64_t)(end - p) || payload != hsize + wt + wts + dsize)
                goto general;
            topic[n] = int_value(t1, p + hsize);
            time[n] = int_value(t2, p + hsize + wt);
            size[n] = (int64_t)dsize;
            n++;
            if (w->nwant) { /* the whole record is on the page: so is its blob */
                w->n = n;
                if (blob_head(w, topic[n - 1], p + hsize + wt + wts, dsize, dsize)) return -1;
            }
            continue;
        }
    general:
        w->n = n;
        if (cell(w, page + ptr, end, ptr + FAR > usable)) return -1;
        n = w->n;
    }
    w->n = n;
    return 0;
}

/* Children of an interior page, pushed right to left so the leftmost is visited first. */
static int interior(Walk *w, const uint8_t *page) {
    const uint64_t usable = w->usable;
    uint64_t ncells = be16(page + 3);
    if (12 + 2 * ncells > usable) FAIL("interior page cell count out of range");
    uint64_t need = w->depth + ncells + 1;
    if (need > w->room) { /* the stack holds about tree depth x fan-out pages: grow it */
        uint64_t room = 2 * w->room > need ? 2 * w->room : need;
        uint32_t *grown = realloc(w->stack, room * sizeof(uint32_t));
        if (grown == NULL) return w->nomem = 1, -1;
        w->stack = grown;
        w->room = room;
    }
    for (uint64_t j = ncells + 1; j-- > 0;) {
        uint64_t child;
        if (j == ncells) {
            child = be32(page + 8);
        } else {
            uint64_t ptr = be16(page + 12 + 2 * j);
            if (ptr < 12 + 2 * ncells || ptr + 4 > usable) FAIL("interior cell outside its page");
            child = be32(page + ptr);
        }
        if (child < 2 || child > w->n_pages || (w->seen[child >> 3] >> (child & 7) & 1))
            FAIL("bad or repeated page number in the messages B-tree");
        w->seen[child >> 3] |= (uint8_t)(1 << (child & 7));
        w->stack[w->depth++] = (uint32_t)child;
    }
    return 0;
}

static int call_release(PyObject *release, Walk *w) {
    if (release == Py_None || w->hi <= w->lo) return 0;
    PyObject *r = PyObject_CallFunction(release, "KK", (unsigned long long)w->lo, (unsigned long long)w->hi);
    w->lo = UINT64_MAX;
    w->hi = 0;
    if (r == NULL) return -1;
    Py_DECREF(r);
    return 0;
}

/* A C-contiguous int64 buffer (numpy int64 array), writable when ``write`` is set. */
static int i64_buffer(PyObject *obj, Py_buffer *view, const char *name, int write) {
    if (PyObject_GetBuffer(obj, view, (write ? PyBUF_WRITABLE : 0) | PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0)
        return -1;
    const char *f = view->format;
    if (f != NULL && (*f == '<' || *f == '=' || *f == '@')) f++;
    if (view->itemsize != 8 || f == NULL || (strcmp(f, "l") && strcmp(f, "q"))) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_TypeError, "%s must be a contiguous int64 array", name);
        return -1;
    }
    return 0;
}

/* A C-contiguous writable byte buffer. */
static int u8_buffer(PyObject *obj, Py_buffer *view, const char *name) {
    if (PyObject_GetBuffer(obj, view, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0) return -1;
    (void)name;
    return 0;
}

/* decode() and decode_heads(): ``heads`` NULL for decode(). */
static PyObject *walk_table(PyObject *args, int with_heads) {
    Py_buffer src, vt, vs, vz, vw, vh, vr;
    unsigned long long root, page_size, usable, step;
    PyObject *ot, *os, *oz, *release, *ow = NULL, *oh = NULL, *orow = NULL;
    if (with_heads) {
        if (!PyArg_ParseTuple(args, "y*KKKOOOOKOOO", &src, &root, &page_size, &usable, &ot, &os, &oz, &release,
                              &step, &ow, &oh, &orow))
            return NULL;
    } else if (!PyArg_ParseTuple(args, "y*KKKOOOOK", &src, &root, &page_size, &usable, &ot, &os, &oz, &release,
                                 &step)) {
        return NULL;
    }
    PyObject *result = NULL;
    int have_t = 0, have_s = 0, have_z = 0, have_w = 0, have_h = 0, have_r = 0;
    Walk w = {0}; /* zeroed first: every exit below frees w.seen and w.stack */
    if (i64_buffer(ot, &vt, "topic", 1) < 0) goto done;
    have_t = 1;
    if (i64_buffer(os, &vs, "time", 1) < 0) goto done;
    have_s = 1;
    if (i64_buffer(oz, &vz, "size", 1) < 0) goto done;
    have_z = 1;
    if (vt.len != vs.len || vt.len != vz.len) {
        PyErr_SetString(PyExc_ValueError, "output arrays differ in length");
        goto done;
    }
    if (with_heads) {
        if (i64_buffer(ow, &vw, "want", 0) < 0) goto done;
        have_w = 1;
        if (u8_buffer(oh, &vh, "heads") < 0) goto done;
        have_h = 1;
        if (i64_buffer(orow, &vr, "rows", 1) < 0) goto done;
        have_r = 1;
        if (vr.len != vt.len || vr.len == 0 || vh.len % (vr.len / 8) || vw.len == 0) {
            PyErr_SetString(PyExc_ValueError, "heads/rows/want do not match the outputs");
            goto done;
        }
    }
    if (page_size < 512 || page_size > 65536 || (page_size & (page_size - 1)) || usable < 480 || usable > page_size) {
        PyErr_SetString(Malformed, "bad page size");
        goto done;
    }
    w = (Walk){.buf = src.buf, .page_size = page_size, .usable = usable,
               .n_pages = (uint64_t)src.len / page_size, .topic = vt.buf, .time = vs.buf,
               .size = vz.buf, .cap = vt.len / 8, .lo = UINT64_MAX, .room = 64};
    if (with_heads) {
        w.want = vw.buf;
        w.nwant = vw.len / 8;
        w.heads = vh.buf;
        w.rows = vr.buf;
        w.head = (uint64_t)(vh.len / (vr.len / 8));
    }
    if (root < 2 || root > w.n_pages) {
        PyErr_SetString(Malformed, "bad root page of the messages table");
        goto done;
    }
    if (w.n_pages > UINT32_MAX) {
        PyErr_SetString(Malformed, "file too large for an SQLite database");
        goto done;
    }
    w.seen = calloc(w.n_pages / 8 + 1, 1);
    w.stack = malloc(w.room * sizeof(uint32_t));
    if (w.seen == NULL || w.stack == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    uint64_t since = 0;
    w.stack[w.depth++] = (uint32_t)root;
    w.seen[root >> 3] |= (uint8_t)(1 << (root & 7));
    int failed = 0;
    PyThreadState *ts = PyEval_SaveThread();
    while (w.depth && !w.err && !w.nomem) {
        uint64_t off = (uint64_t)(w.stack[--w.depth] - 1) * page_size;
        const uint8_t *page = w.buf + off;
        touched(&w, off);
        if (page[0] == 0x0D) {
            leaf(&w, page);
        } else if (page[0] == 0x05) {
            interior(&w, page);
        } else {
            w.err = "a page of the messages B-tree is not a table B-tree page";
        }
        since += page_size;
        if (step && since >= step && release != Py_None) {
            since = 0;
            PyEval_RestoreThread(ts);
            failed = call_release(release, &w);
            ts = PyEval_SaveThread();
            if (failed) break;
        }
    }
    PyEval_RestoreThread(ts);
    if (failed) goto done;
    if (w.nomem) {
        PyErr_NoMemory();
        goto done;
    }
    if (w.err) {
        PyErr_SetString(Malformed, w.err);
        goto done;
    }
    if (call_release(release, &w) < 0) goto done;
    result = with_heads ? Py_BuildValue("nn", w.n, w.m) : PyLong_FromSsize_t(w.n);
done:
    free(w.seen);
    free(w.stack);
    if (have_t) PyBuffer_Release(&vt);
    if (have_s) PyBuffer_Release(&vs);
    if (have_z) PyBuffer_Release(&vz);
    if (have_w) PyBuffer_Release(&vw);
    if (have_h) PyBuffer_Release(&vh);
    if (have_r) PyBuffer_Release(&vr);
    PyBuffer_Release(&src);
    return result;
}

static PyObject *decode(PyObject *self, PyObject *args) { return walk_table(args, 0); }

static PyObject *decode_heads(PyObject *self, PyObject *args) { return walk_table(args, 1); }

#define MAX_SPAN (1 << 22) /* widest id range the lookup table covers */

static PyObject *group(PyObject *self, PyObject *args) {
    Py_buffer b[7];
    int have = 0;
    PyObject *result = NULL;
    int32_t *slot = NULL;
    static const char *names[7] = {"tids", "times", "sizes", "ids", "counts", "nbytes", "out_times"};
    PyObject *objs[7];
    if (!PyArg_ParseTuple(args, "OOOOOOO", &objs[0], &objs[1], &objs[2], &objs[3], &objs[4], &objs[5], &objs[6]))
        return NULL;
    for (; have < 7; have++)
        if (i64_buffer(objs[have], &b[have], names[have], have >= 4) < 0) goto done;
    const int64_t *tids = b[0].buf, *times = b[1].buf, *sizes = b[2].buf, *ids = b[3].buf;
    int64_t *counts = b[4].buf, *nbytes = b[5].buf, *out = b[6].buf;
    Py_ssize_t n = b[0].len / 8, k = b[3].len / 8;
    if (b[1].len != b[0].len || b[2].len != b[0].len || b[6].len != b[0].len || b[4].len != b[3].len ||
        b[5].len != b[3].len) {
        PyErr_SetString(PyExc_ValueError, "array lengths do not match");
        goto done;
    }
    result = Py_False;
    if (k == 0) {
        if (n == 0) result = Py_True;
        goto done;
    }
    int64_t lo = ids[0], hi = ids[0];
    for (Py_ssize_t j = 1; j < k; j++) {
        if (ids[j] < lo) lo = ids[j];
        if (ids[j] > hi) hi = ids[j];
    }
    if ((uint64_t)hi - (uint64_t)lo >= MAX_SPAN) goto done;
    uint64_t span = (uint64_t)hi - (uint64_t)lo + 1;
    slot = malloc(span * sizeof(int32_t));
    if (slot == NULL) {
        result = NULL;
        PyErr_NoMemory();
        goto done;
    }
    memset(slot, 0xff, span * sizeof(int32_t));
    for (Py_ssize_t j = 0; j < k; j++) {
        if (slot[ids[j] - lo] >= 0) goto done; /* repeated id */
        slot[ids[j] - lo] = (int32_t)j;
        counts[j] = 0;
        nbytes[j] = 0;
    }
    uint64_t *bytes = (uint64_t *)nbytes;
    for (Py_ssize_t i = 0; i < n; i++) {
        uint64_t d = (uint64_t)tids[i] - (uint64_t)lo;
        if (d >= span || slot[d] < 0) goto done;
        int32_t s = slot[d];
        counts[s]++;
        bytes[s] += (uint64_t)sizes[i];
        if (bytes[s] > (uint64_t)INT64_MAX) goto done;
    }
    Py_ssize_t at = 0;
    for (Py_ssize_t j = 0; j < k; j++) { /* counts become start offsets for the scatter */
        Py_ssize_t c = counts[j];
        counts[j] = at;
        at += c;
    }
    for (Py_ssize_t i = 0; i < n; i++) out[counts[slot[tids[i] - lo]]++] = times[i];
    for (Py_ssize_t j = k; j-- > 0;) counts[j] -= j ? counts[j - 1] : 0; /* back to counts */
    result = Py_True;
done:
    free(slot);
    for (int j = 0; j < have; j++) PyBuffer_Release(&b[j]);
    Py_XINCREF(result);
    return result;
}

static PyMethodDef methods[] = {
    {"decode", decode, METH_VARARGS, "Decode rosbag2's messages table from SQLite B-tree pages."},
    {"decode_heads", decode_heads, METH_VARARGS, "decode(), with the first bytes of the wanted topics' blobs."},
    {"group", group, METH_VARARGS, "Stable counting sort of times by topic id."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_sqlitecells", NULL, -1, methods};

PyMODINIT_FUNC PyInit__sqlitecells(void) {
    for (int t = 0; t < 256; t++) WIDTH[t] = (int8_t)int_width((uint64_t)t);
    PyObject *m = PyModule_Create(&module);
    if (m == NULL) return NULL;
    Malformed = PyErr_NewException("perfros_bag.ingest._sqlitecells.Malformed", PyExc_ValueError, NULL);
    if (Malformed == NULL || PyModule_AddObjectRef(m, "Malformed", Malformed) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
