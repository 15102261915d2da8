/* The MAVLink router's common case, compiled: see Router._route_datagrams.
 *
 * route(datagrams, start, info, seen, seen_at, own, last_seq, now, boxes, boxes_of, dests,
 *       dests_of, link) walks the datagrams from index ``start`` while each one is a
 * single MAVLink 2 frame of a known id with a good CRC, broadcast (no target, or target
 * system 0), from a source already seen on the link, not using a node's id, and not read
 * at once by a node (``boxes[msgid]`` is not None).  For each it does what the Python path
 * does: counts sequence gaps, marks the system heard at ``now``, keeps it as (bytes,
 * link) in the mailboxes of ``boxes[msgid]`` (dicts of the nodes that read it later, keyed
 * (source << 24) | id), and forwards it: appended to the batch lists and passed to the send
 * callables of ``dests[key]`` (``dests_of(key)`` fills a missing entry, ``boxes_of(msgid)``
 * a missing ``boxes`` entry).  It stops at the first datagram that is anything else and returns
 *
 *     (stop index, frames, bytes, forwarded, mailboxed, sequence numbers lost)
 *
 * for the caller to route that one by the general path and call again after it.  The
 * pure-Python path (backends/mavlink/router.py) is the reference; tests compare the two.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#define STX_V2 0xFD
#define HEADER_V2 10
#define SIGNATURE_LEN 13

/* MAVLink's CRC: CRC-16/MCRF4XX (X.25 polynomial, reflected, initial 0xFFFF, no final
 * xor), one byte at a time as the protocol specifies it. */
static inline uint16_t crc_byte(uint16_t crc, uint8_t b)
{
    uint8_t t = b ^ (uint8_t)(crc & 0xFF);
    t ^= (uint8_t)(t << 4);
    return (uint16_t)((crc >> 8) ^ ((uint16_t)t << 8) ^ ((uint16_t)t << 3) ^ (t >> 4));
}

/* The four fields of an INFO entry: (crc_extra bytes, max_len, target_system offset,
 * target_component offset). */
typedef struct {
    int extra;
    long max_len;
    long sys_ofs;
} msg_info;

static int read_info(PyObject *entry, msg_info *out)
{
    if (!PyTuple_Check(entry) || PyTuple_GET_SIZE(entry) < 3) {
        PyErr_SetString(PyExc_TypeError, "info entries must be (bytes, int, int, int)");
        return -1;
    }
    PyObject *extra = PyTuple_GET_ITEM(entry, 0);
    if (!PyBytes_Check(extra) || PyBytes_GET_SIZE(extra) != 1) {
        PyErr_SetString(PyExc_TypeError, "an info entry's CRC extra must be one byte");
        return -1;
    }
    out->extra = (unsigned char)PyBytes_AS_STRING(extra)[0];
    out->max_len = PyLong_AsLong(PyTuple_GET_ITEM(entry, 1));
    out->sys_ofs = PyLong_AsLong(PyTuple_GET_ITEM(entry, 2));
    if (PyErr_Occurred())
        return -1;
    return 0;
}

/* d[k], computed by fill(k) and stored when missing; a borrowed reference (NULL: error). */
static PyObject *cached(PyObject *d, PyObject *k, PyObject *fill)
{
    PyObject *v = PyDict_GetItemWithError(d, k);
    if (v != NULL || PyErr_Occurred())
        return v;
    v = PyObject_CallOneArg(fill, k);
    if (v == NULL)
        return NULL;
    int rc = PyDict_SetItem(d, k, v);
    Py_DECREF(v);  /* the dict holds it */
    return rc < 0 ? NULL : v;
}

static PyObject *route(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 13) {
        PyErr_SetString(PyExc_TypeError, "route() takes 13 arguments");
        return NULL;
    }
    PyObject *datagrams = args[0];
    Py_ssize_t i = PyLong_AsSsize_t(args[1]);
    PyObject *info_of = args[2], *seen = args[3], *seen_at = args[4], *own = args[5];
    PyObject *last_seq = args[6], *now = args[7], *boxes = args[8], *boxes_of = args[9];
    PyObject *dests = args[10], *dests_of = args[11], *link = args[12];
    if (i == -1 && PyErr_Occurred())
        return NULL;
    if (!PyList_Check(datagrams) || !PyDict_Check(info_of) || !PyAnySet_Check(seen)
        || !PyDict_Check(seen_at) || !PyDict_Check(own) || !PyDict_Check(last_seq)
        || !PyDict_Check(boxes) || !PyDict_Check(dests)) {
        PyErr_SetString(PyExc_TypeError, "route(): a list, then dicts and a set");
        return NULL;
    }
    long long frames = 0, nbytes = 0, forwarded = 0, mailboxed = 0, lost = 0;
    PyObject *key_obj = NULL, *sys_obj = NULL, *msgid_obj = NULL, *item = NULL;
    int failed = 0;

    for (; i < PyList_GET_SIZE(datagrams); i++) {
        PyObject *it = PyList_GET_ITEM(datagrams, i);
        if (!PyBytes_CheckExact(it))
            break;
        item = Py_NewRef(it);  /* held across the Python calls below */
        const unsigned char *d = (const unsigned char *)PyBytes_AS_STRING(item);
        Py_ssize_t n = PyBytes_GET_SIZE(item);
        if (n <= HEADER_V2 + 2 || d[0] != STX_V2 || (d[2] & 0xFE))
            break;
        long plen = d[1];
        long crc_at = HEADER_V2 + plen;
        if (crc_at + 2 + (d[2] ? SIGNATURE_LEN : 0) != n)
            break;
        long msgid = d[7] | (d[8] << 8) | (d[9] << 16);
        int sysid = d[5];
        long key = ((long)sysid << 8) | d[6];

        msgid_obj = PyLong_FromLong(msgid);
        if (msgid_obj == NULL) { failed = 1; break; }
        PyObject *entry = PyDict_GetItemWithError(info_of, msgid_obj);
        if (entry == NULL) {
            if (PyErr_Occurred()) failed = 1;
            break;
        }
        msg_info info;
        if (read_info(entry, &info) < 0) { failed = 1; break; }
        if (plen > info.max_len)
            break;
        key_obj = PyLong_FromLong(key);
        sys_obj = PyLong_FromLong(sysid);
        if (key_obj == NULL || sys_obj == NULL) { failed = 1; break; }
        int r = PySet_Contains(seen, key_obj);
        if (r <= 0) { failed = r < 0; break; }
        r = PyDict_Contains(seen_at, sys_obj);
        if (r <= 0) { failed = r < 0; break; }
        r = PyDict_Contains(own, sys_obj);
        if (r != 0) { failed = r < 0; break; }
        long so = info.sys_ofs;
        long tsys = so < 0 ? -1 : (so < plen ? d[HEADER_V2 + so] : 0);
        PyObject *box = cached(boxes, msgid_obj, boxes_of);
        if (box == NULL) { failed = 1; break; }
        if (tsys > 0 || box == Py_None)
            break;
        uint16_t crc = 0xFFFF;
        for (long k = 1; k < crc_at; k++)
            crc = crc_byte(crc, d[k]);
        crc = crc_byte(crc, (uint8_t)info.extra);
        if (crc != (d[crc_at] | (d[crc_at + 1] << 8)))
            break;

        /* the frame takes this path: its effects */
        int seq = d[4];
        PyObject *last = PyDict_GetItemWithError(last_seq, key_obj);
        if (last == NULL && PyErr_Occurred()) { failed = 1; break; }
        if (last != NULL) {
            long gap = (seq - PyLong_AsLong(last) - 1) & 0xFF;
            if (gap == -1 && PyErr_Occurred()) { failed = 1; break; }
            lost += gap;
        }
        PyObject *seq_obj = PyLong_FromLong(seq);  /* a cached small int */
        if (seq_obj == NULL) { failed = 1; break; }
        r = PyDict_SetItem(last_seq, key_obj, seq_obj);
        Py_DECREF(seq_obj);
        if (r < 0 || PyDict_SetItem(seen_at, sys_obj, now) < 0) { failed = 1; break; }
        frames++;
        nbytes += n;
        if (!PyTuple_Check(box)) {
            PyErr_SetString(PyExc_TypeError, "boxes_of() must give a tuple or None");
            failed = 1;
            break;
        }
        Py_ssize_t nbox = PyTuple_GET_SIZE(box);
        if (nbox) {
            PyObject *box_key = PyLong_FromLongLong(((long long)key << 24) | msgid);
            PyObject *kept = box_key ? PyTuple_Pack(2, item, link) : NULL;
            for (Py_ssize_t b = 0; kept != NULL && b < nbox; b++) {
                PyObject *mailbox = PyTuple_GET_ITEM(box, b);
                if (!PyDict_Check(mailbox)) {
                    PyErr_SetString(PyExc_TypeError, "boxes_of() must give dicts");
                    failed = 1;
                } else if (PyDict_SetItem(mailbox, box_key, kept) < 0) {
                    failed = 1;
                }
                if (failed)
                    break;
            }
            if (kept == NULL)
                failed = 1;
            Py_XDECREF(kept);
            Py_XDECREF(box_key);
            if (failed)
                break;
            mailboxed += nbox;
        }
        PyObject *entry_d = cached(dests, key_obj, dests_of);
        if (entry_d == NULL) { failed = 1; break; }
        if (!PyTuple_Check(entry_d) || PyTuple_GET_SIZE(entry_d) != 2
            || !PyTuple_Check(PyTuple_GET_ITEM(entry_d, 0))
            || !PyTuple_Check(PyTuple_GET_ITEM(entry_d, 1))) {
            PyErr_SetString(PyExc_TypeError, "dests_of() must give (lists, send callables)");
            failed = 1;
            break;
        }
        Py_INCREF(entry_d);  /* a send below may run any Python */
        PyObject *sinks = PyTuple_GET_ITEM(entry_d, 0), *sends = PyTuple_GET_ITEM(entry_d, 1);
        for (Py_ssize_t s = 0; s < PyTuple_GET_SIZE(sinks) && !failed; s++) {
            PyObject *sink = PyTuple_GET_ITEM(sinks, s);
            if (!PyList_Check(sink)) {
                PyErr_SetString(PyExc_TypeError, "a batch sink must be a list");
                failed = 1;
            } else if (PyList_Append(sink, item) < 0) {
                failed = 1;
            } else {
                forwarded++;
            }
        }
        for (Py_ssize_t s = 0; s < PyTuple_GET_SIZE(sends) && !failed; s++) {
            PyObject *res = PyObject_CallOneArg(PyTuple_GET_ITEM(sends, s), item);
            if (res == NULL) {
                failed = 1;
                break;
            }
            r = PyObject_IsTrue(res);
            Py_DECREF(res);
            if (r < 0)
                failed = 1;
            else
                forwarded += r;
        }
        Py_DECREF(entry_d);
        if (failed)
            break;
        Py_CLEAR(key_obj);
        Py_CLEAR(sys_obj);
        Py_CLEAR(msgid_obj);
        Py_CLEAR(item);
    }
    Py_XDECREF(key_obj);
    Py_XDECREF(sys_obj);
    Py_XDECREF(msgid_obj);
    Py_XDECREF(item);
    if (failed)
        return NULL;
    return Py_BuildValue("(nLLLLL)", i, frames, nbytes, forwarded, mailboxed, lost);
}


#ifdef __linux__
#include <errno.h>
#include <string.h>
#include <poll.h>
#include <sys/epoll.h>
#include <sys/socket.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

/* epoll_wait with a timeout in nanoseconds (epoll_pwait2, Linux 5.11), or whole milliseconds
 * rounded up where the kernel has no epoll_pwait2 */
static int wait_ns(int ep, struct epoll_event *evs, int max, double left)
{
    static int no_pwait2 = 0;
#ifdef SYS_epoll_pwait2
    if (!no_pwait2) {
        time_t sec = (time_t)left;
        struct timespec ts = {sec, (long)((left - (double)sec) * 1e9)};
        long r = syscall(SYS_epoll_pwait2, ep, evs, max, &ts, NULL, 0);
        if (r >= 0 || errno != ENOSYS)
            return (int)r;
        no_pwait2 = 1;
    }
#endif
    return epoll_wait(ep, evs, max, (int)(left * 1e3) + 1);
}

/* obj.name += n (n > 0 only: a zero adds nothing); -1: error */
static int add_to(PyObject *obj, PyObject *name, long long n)
{
    if (n == 0)
        return 0;
    PyObject *v = PyObject_GetAttr(obj, name);
    if (v == NULL)
        return -1;
    PyObject *d = PyLong_FromLongLong(n);
    PyObject *sum = d ? PyNumber_Add(v, d) : NULL;
    Py_DECREF(v);
    Py_XDECREF(d);
    if (sum == NULL)
        return -1;
    int rc = PyObject_SetAttr(obj, name, sum);
    Py_DECREF(sum);
    return rc;
}

static int truthy_attr(PyObject *obj, PyObject *name)
{
    PyObject *v = PyObject_GetAttr(obj, name);
    if (v == NULL)
        return -1;
    int r = PyObject_IsTrue(v);
    Py_DECREF(v);
    return r;
}

static double monotonic_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

/* interned attribute names */
static PyObject *s_batch, *s_now, *s_received_bytes, *s_seq_lost, *s_frames, *s_bytes_in,
    *s_rx_frames, *s_rx_bytes, *s_forwarded, *s_mailboxed, *s_up, *s_writing,
    *s_flush_scheduled, *s_submitted, *s_accepted, *s_sent_frames, *s_sent_bytes,
    *s_tx_frames, *s_tx_bytes, *s_acquire, *s_release, *s_tap, *s_verifier, *s_forward,
    *s_batching;

static int intern_names(void)
{
#define IN(var, text) if ((var = PyUnicode_InternFromString(text)) == NULL) return -1
    IN(s_batch, "_batch"); IN(s_now, "_now"); IN(s_received_bytes, "received_bytes");
    IN(s_seq_lost, "seq_lost"); IN(s_frames, "frames"); IN(s_bytes_in, "bytes_in");
    IN(s_rx_frames, "rx_frames"); IN(s_rx_bytes, "rx_bytes"); IN(s_forwarded, "forwarded");
    IN(s_mailboxed, "mailboxed"); IN(s_up, "_up"); IN(s_writing, "_writing");
    IN(s_flush_scheduled, "_flush_scheduled"); IN(s_submitted, "submitted");
    IN(s_accepted, "accepted"); IN(s_sent_frames, "sent_frames"); IN(s_sent_bytes, "sent_bytes");
    IN(s_tx_frames, "tx_frames"); IN(s_tx_bytes, "tx_bytes"); IN(s_acquire, "acquire");
    IN(s_release, "release"); IN(s_tap, "tap"); IN(s_verifier, "verifier");
    IN(s_forward, "forward"); IN(s_batching, "_batching");
#undef IN
    return 0;
}


/* One out link of a lane: (fd, send headers' address, list, link, engine, engine stats,
 * link counters). */
enum { OUT_FD, OUT_HDRS, OUT_LIST, OUT_LINK, OUT_ENGINE, OUT_STATS, OUT_COUNTERS, OUT_N };

/* The lane's hold (the port engine's COALESCE_S): a read at readiness that finds fewer than
 * `burst_min` datagrams, within `gap` s of the last read, is a paced stream: the port is
 * then read again `hold` s after each read instead of at once, while those reads find
 * datagrams.  A read that finds `burst_min` or more at readiness is a burst, read whole as it
 * comes (in C a wake-up costs less than holding it: tools/bench/README.md).  Every
 * HOLD_PROBE holds, one read waits for readiness again: so a stream of bursts that once
 * looked paced is found out. */
#define HOLD_PROBE 64
typedef struct {
    double hold, gap;
    int burst_min;
} hold_rule;

static PyObject *lane_cycles(PyObject *module, int ep, int rx_fd, struct mmsghdr *rhdrs,
                             unsigned int batch, double deadline, PyObject *expect,
                             PyObject *rargs, PyObject *outs, PyObject *in_stats,
                             PyObject *framer, PyObject *counters, PyObject *router,
                             PyObject *rstats, PyObject *acquire, PyObject *release,
                             PyObject *batching, int loop_fd, const hold_rule *rule);

static PyObject *lane(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 17) {
        PyErr_SetString(PyExc_TypeError, "lane() takes 17 arguments");
        return NULL;
    }
    int rx_fd = (int)PyLong_AsLong(args[0]);
    struct mmsghdr *rhdrs = (struct mmsghdr *)(uintptr_t)PyLong_AsUnsignedLongLong(args[1]);
    unsigned int batch = (unsigned int)PyLong_AsUnsignedLong(args[2]);
    int loop_fd = (int)PyLong_AsLong(args[3]);
    double deadline = PyFloat_AsDouble(args[4]);
    PyObject *expect = args[5], *rargs = args[6], *outs = args[7], *in_stats = args[8];
    PyObject *framer = args[9], *counters = args[10], *router = args[11], *lock = args[12];
    PyObject *batching = args[13];
    hold_rule rule = {PyFloat_AsDouble(args[14]), PyFloat_AsDouble(args[15]),
                      (int)PyLong_AsLong(args[16])};
    PyObject *rstats = PyObject_GetAttrString(router, "stats");
    if (rstats == NULL)
        return NULL;
    Py_DECREF(rstats);  /* the router holds it */
    if (PyErr_Occurred())
        return NULL;
    if (!PyTuple_Check(rargs) || PyTuple_GET_SIZE(rargs) != 10 || !PyTuple_Check(outs)
        || (expect != Py_None && !PyBytes_Check(expect))) {
        PyErr_SetString(PyExc_TypeError, "lane(): bad arguments");
        return NULL;
    }
    Py_ssize_t nouts = PyTuple_GET_SIZE(outs);
    for (Py_ssize_t k = 0; k < nouts; k++) {
        PyObject *o = PyTuple_GET_ITEM(outs, k);
        if (!PyTuple_Check(o) || PyTuple_GET_SIZE(o) != OUT_N
            || !PyList_Check(PyTuple_GET_ITEM(o, OUT_LIST))) {
            PyErr_SetString(PyExc_TypeError, "lane(): bad out link");
            return NULL;
        }
    }
    PyObject *acquire = PyObject_GetAttr(lock, s_acquire);
    PyObject *release = acquire ? PyObject_GetAttr(lock, s_release) : NULL;
    /* (its own descriptor failing is the lane's failure, not the port's: RuntimeError, so
     * the engine turns the lane off rather than reopening a port that reads fine) */
    int ep = release ? epoll_create1(EPOLL_CLOEXEC) : -1;
    if (release != NULL && ep < 0)
        PyErr_Format(PyExc_RuntimeError, "lane(): epoll_create1: %s", strerror(errno));
    if (ep >= 0) {
        struct epoll_event e1 = {.events = EPOLLIN, .data.u32 = 0};
        struct epoll_event e2 = {.events = EPOLLIN, .data.u32 = 1};
        if (epoll_ctl(ep, EPOLL_CTL_ADD, rx_fd, &e1) < 0
            || epoll_ctl(ep, EPOLL_CTL_ADD, loop_fd, &e2) < 0) {
            PyErr_Format(PyExc_RuntimeError, "lane(): epoll_ctl: %s", strerror(errno));
            close(ep);
            ep = -1;
        }
    }
    PyObject *out = ep < 0 ? NULL : lane_cycles(module, ep, rx_fd, rhdrs, batch, deadline,
                                                  expect, rargs, outs, in_stats, framer,
                                                  counters, router, rstats, acquire, release,
                                                  batching, loop_fd, &rule);
    if (ep >= 0)
        close(ep);
    Py_XDECREF(acquire);
    Py_XDECREF(release);
    return out;
}

/* lane()'s cycles: wait, read, route, write, until something is for the caller.
 *
 * A cycle's batches are written at the start of the next stretch without the GIL, right
 * before it waits: what a datagram wakes (the receiver) runs while this thread sleeps, as
 * with mavlink-router, instead of preempting it mid-work.  By then they are counted (as
 * flush_batch counts a batch it hands to the port) and the router's lock is free; a short
 * sendmmsg is handed back at once (reason 4) for MmsgSocket.send to go on with. */
static PyObject *lane_cycles(PyObject *module, int ep, int rx_fd, struct mmsghdr *rhdrs,
                             unsigned int batch, double deadline, PyObject *expect,
                             PyObject *rargs, PyObject *outs, PyObject *in_stats,
                             PyObject *framer, PyObject *counters, PyObject *router,
                             PyObject *rstats, PyObject *acquire, PyObject *release,
                             PyObject *batching, int loop_fd, const hold_rule *rule)
{
    Py_ssize_t nouts = PyTuple_GET_SIZE(outs);
    if (nouts > 8) {
        PyErr_SetString(PyExc_ValueError, "lane(): at most 8 out links");
        return NULL;
    }
    int pending = 0;  /* the outs' lists hold a batch to write */
    int holding = 0, holds = 0;  /* see hold_rule */
    int first = 1;  /* the first cycle reads a ready port even when the loop has work too:
                     * each call reads it at least once (the loop never watches it) */
    double done = 0.0;  /* when the port was last read */
    for (;;) {
        struct epoll_event evs[2];
        int r = 0, n = 0, err = 0, loop_ready = 0, port_ready = 0, short_k = -1, short_n = 0;
        int fds[8];
        struct mmsghdr *sh[8];
        Py_ssize_t ms[8];
        for (Py_ssize_t k = 0; pending && k < nouts; k++) {
            PyObject *o = PyTuple_GET_ITEM(outs, k);
            fds[k] = (int)PyLong_AsLong(PyTuple_GET_ITEM(o, OUT_FD));
            sh[k] = (struct mmsghdr *)(uintptr_t)PyLong_AsUnsignedLongLong(
                PyTuple_GET_ITEM(o, OUT_HDRS));
            ms[k] = PyList_GET_SIZE(PyTuple_GET_ITEM(o, OUT_LIST));
        }
        if (PyErr_Occurred())
            return NULL;
        double now = monotonic_s();
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t k = 0; pending && k < nouts; k++) {
            if (ms[k] == 0)
                continue;
            int sent = sendmmsg(fds[k], sh[k], (unsigned int)ms[k], MSG_DONTWAIT);
            if (sent != ms[k]) {
                short_k = (int)k;
                short_n = sent < 0 ? -errno : sent;
                break;
            }
        }
        if (short_k < 0) {
            if (pending)
                now = monotonic_s();
            if (now < deadline && holding) {  /* the loop only, for the hold */
                double left = deadline - now < rule->hold ? deadline - now : rule->hold;
                time_t sec = (time_t)left;
                struct timespec ts = {sec, (long)((left - (double)sec) * 1e9)};
                struct pollfd lp = {loop_fd, POLLIN, 0};
                r = ppoll(&lp, 1, &ts, NULL);
                if (r != 0 || left < rule->hold)
                    loop_ready = 1;  /* the loop has work, or its timer is due */
                else
                    port_ready = 1;  /* read what came meanwhile */
                if (port_ready) {
                    n = recvmmsg(rx_fd, rhdrs, batch, MSG_DONTWAIT, NULL);
                    if (n < 0)
                        err = errno;
                }
            } else if (now < deadline) {
                r = wait_ns(ep, evs, 2, deadline - now);
                for (int i = 0; i < r; i++) {
                    if (evs[i].data.u32 == 1 || (evs[i].events & ~EPOLLIN))
                        loop_ready = 1;
                    else
                        port_ready = 1;
                }
                if (r > 0 && port_ready && (first || !loop_ready)) {
                    n = recvmmsg(rx_fd, rhdrs, batch, MSG_DONTWAIT, NULL);
                    if (n < 0)
                        err = errno;
                }
            } else {
                loop_ready = 1;  /* the loop's timer is due */
            }
        }
        Py_END_ALLOW_THREADS
        if (pending) {
            pending = 0;
            if (short_k >= 0)  /* the lists from short_k on: the caller writes them */
                return Py_BuildValue("(iii)", 4, short_k, short_n);
            for (Py_ssize_t k = 0; k < nouts; k++) {
                PyObject *list = PyTuple_GET_ITEM(PyTuple_GET_ITEM(outs, k), OUT_LIST);
                if (PyList_SetSlice(list, 0, PyList_GET_SIZE(list), NULL) < 0)
                    return NULL;
            }
        }
        if (r < 0 || (loop_ready && !(first && port_ready)))
            return Py_BuildValue("(i)", 0);  /* the loop has work (or the port: its path) */
        first = 0;
        if (!port_ready)
            continue;
        if (n < 0 && err != EAGAIN && err != EINTR)
            return Py_BuildValue("(iOOi)", 1, Py_None, Py_None, err);
        if (n < 0)
            n = 0;
        {  /* the hold's rule, as PortEngine._read_batches keeps it */
            double t = monotonic_s();
            int dense = t - done < rule->gap;
            done = t;
            if (holding) {
                holding = n > 0 && dense && ++holds < HOLD_PROBE;
            } else {
                holding = n > 0 && n < rule->burst_min && dense && rule->hold > 0;
                holds = 0;
            }
        }
        if (n == 0)
            continue;
        PyObject *datagrams = PyList_New(n);
        if (datagrams == NULL)
            return NULL;
        long long in_bytes = 0;
        int same = 1;
        const char *want = expect == Py_None ? NULL : PyBytes_AS_STRING(expect);
        Py_ssize_t want_len = expect == Py_None ? 0 : PyBytes_GET_SIZE(expect);
        for (int i = 0; i < n; i++) {
            struct iovec *iov = rhdrs[i].msg_hdr.msg_iov;
            size_t len = rhdrs[i].msg_len;
            if (len > iov->iov_len)
                len = iov->iov_len;
            PyObject *b = PyBytes_FromStringAndSize((const char *)iov->iov_base, (Py_ssize_t)len);
            if (b == NULL) {
                Py_DECREF(datagrams);
                return NULL;
            }
            PyList_SET_ITEM(datagrams, i, b);
            in_bytes += (long long)len;
            if (want != NULL && ((Py_ssize_t)rhdrs[i].msg_hdr.msg_namelen != want_len
                                 || memcmp(rhdrs[i].msg_hdr.msg_name, want, (size_t)want_len)))
                same = 0;
        }
        if (!same) {  /* a sender other than the latest peer: the port's own path */
            PyObject *raws = PyList_New(n);
            for (int i = 0; raws != NULL && i < n; i++) {
                PyObject *raw = PyBytes_FromStringAndSize(
                    (const char *)rhdrs[i].msg_hdr.msg_name,
                    (Py_ssize_t)rhdrs[i].msg_hdr.msg_namelen);
                if (raw == NULL)
                    Py_CLEAR(raws);
                else
                    PyList_SET_ITEM(raws, i, raw);
            }
            if (raws == NULL) {
                Py_DECREF(datagrams);
                return NULL;
            }
            return Py_BuildValue("(iNNi)", 1, datagrams, raws, 0);
        }
        /* route them, as Router.receive_many does, under the router's lock */
        PyObject *got = PyObject_CallNoArgs(acquire);
        if (got == NULL) {
            Py_DECREF(datagrams);
            return NULL;
        }
        Py_DECREF(got);
        /* what the lane was set up for still holds (another thread may have set a tap, a
         * key or another link meanwhile): else these go the port's way, and the lane ends */
        PyObject *tap = PyObject_GetAttr(router, s_tap);
        PyObject *ver = tap ? PyObject_GetAttr(router, s_verifier) : NULL;
        PyObject *fwd = ver ? PyObject_GetAttr(router, s_forward) : NULL;
        PyObject *bt = fwd ? PyObject_GetAttr(router, s_batching) : NULL;
        int same_setup = bt == NULL ? -1 : (tap == Py_None && ver == Py_None && bt == batching);
        if (same_setup == 1) {
            same_setup = PyObject_IsTrue(fwd);
        }
        Py_XDECREF(tap);
        Py_XDECREF(ver);
        Py_XDECREF(fwd);
        Py_XDECREF(bt);
        if (same_setup != 1) {
            PyObject *done = PyObject_CallNoArgs(release);
            Py_XDECREF(done);
            if (same_setup < 0 || done == NULL) {
                Py_DECREF(datagrams);
                return NULL;
            }
            return Py_BuildValue("(iN)", 5, datagrams);
        }
        PyObject *now_obj = PyFloat_FromDouble(monotonic_s());
        int bad = now_obj == NULL || PyObject_SetAttr(router, s_now, now_obj) < 0
                  || add_to(in_stats, s_received_bytes, in_bytes) < 0;
        for (Py_ssize_t k = 0; !bad && k < nouts; k++) {
            PyObject *o = PyTuple_GET_ITEM(outs, k);
            bad = PyObject_SetAttr(PyTuple_GET_ITEM(o, OUT_LINK), s_batch,
                                   PyTuple_GET_ITEM(o, OUT_LIST)) < 0;
        }
        PyObject *res = NULL;
        if (!bad) {
            PyObject *zero = PyLong_FromLong(0);
            PyObject *rv[13] = {datagrams, zero,
                PyTuple_GET_ITEM(rargs, 0), PyTuple_GET_ITEM(rargs, 1),
                PyTuple_GET_ITEM(rargs, 2), PyTuple_GET_ITEM(rargs, 3),
                PyTuple_GET_ITEM(rargs, 4), now_obj, PyTuple_GET_ITEM(rargs, 5),
                PyTuple_GET_ITEM(rargs, 6), PyTuple_GET_ITEM(rargs, 7),
                PyTuple_GET_ITEM(rargs, 8), PyTuple_GET_ITEM(rargs, 9)};
            res = zero ? route(module, rv, 13) : NULL;
            Py_XDECREF(zero);
        }
        Py_XDECREF(now_obj);
        Py_ssize_t stop = 0;
        long long f = 0, b = 0, fw = 0, mb = 0, lost = 0;
        if (res == NULL || !PyArg_ParseTuple(res, "nLLLLL", &stop, &f, &b, &fw, &mb, &lost))
            bad = 1;
        Py_XDECREF(res);
        if (!bad)
            bad = add_to(counters, s_seq_lost, lost) < 0 || add_to(framer, s_frames, f) < 0
                  || add_to(framer, s_bytes_in, b) < 0 || add_to(counters, s_rx_frames, f) < 0
                  || add_to(counters, s_rx_bytes, b) < 0
                  || add_to(rstats, s_forwarded, fw) < 0
                  || add_to(rstats, s_mailboxed, mb) < 0;
        if (bad) {  /* (the caller flushes and releases: the lock is held) */
            Py_DECREF(datagrams);
            return NULL;
        }
        if (stop < n)  /* one for the general path: the caller goes on from there */
            return Py_BuildValue("(iNn)", 2, datagrams, stop);
        Py_DECREF(datagrams);
        /* each link's batch: counted as flush_batch counts it, written at the next stretch */
        for (Py_ssize_t k = 0; k < nouts; k++) {
            PyObject *o = PyTuple_GET_ITEM(outs, k);
            Py_ssize_t m = PyList_GET_SIZE(PyTuple_GET_ITEM(o, OUT_LIST));
            if (m == 0)
                continue;
            PyObject *engine = PyTuple_GET_ITEM(o, OUT_ENGINE);
            int up = truthy_attr(engine, s_up), wr = truthy_attr(engine, s_writing);
            int fs = truthy_attr(engine, s_flush_scheduled);
            if (up < 0 || wr < 0 || fs < 0)
                return NULL;
            if (!up || wr || fs || m > (Py_ssize_t)batch)
                return Py_BuildValue("(inO)", 3, k, Py_None);  /* its queue: the caller */
        }
        for (Py_ssize_t k = 0; k < nouts; k++) {
            PyObject *o = PyTuple_GET_ITEM(outs, k);
            PyObject *list = PyTuple_GET_ITEM(o, OUT_LIST);
            Py_ssize_t m = PyList_GET_SIZE(list);
            if (PyObject_SetAttr(PyTuple_GET_ITEM(o, OUT_LINK), s_batch, Py_None) < 0)
                return NULL;
            if (m == 0)
                continue;
            struct mmsghdr *shdrs = (struct mmsghdr *)(uintptr_t)PyLong_AsUnsignedLongLong(
                PyTuple_GET_ITEM(o, OUT_HDRS));
            if (PyErr_Occurred())
                return NULL;
            long long out_bytes = 0;
            for (Py_ssize_t i = 0; i < m; i++) {  /* the list keeps each alive until written */
                PyObject *d = PyList_GET_ITEM(list, i);
                struct iovec *iov = shdrs[i].msg_hdr.msg_iov;
                iov->iov_base = PyBytes_AS_STRING(d);
                iov->iov_len = (size_t)PyBytes_GET_SIZE(d);
                out_bytes += PyBytes_GET_SIZE(d);
            }
            PyObject *es = PyTuple_GET_ITEM(o, OUT_STATS), *lc = PyTuple_GET_ITEM(o, OUT_COUNTERS);
            if (add_to(es, s_submitted, m) < 0 || add_to(es, s_accepted, m) < 0
                || add_to(es, s_sent_frames, m) < 0 || add_to(es, s_sent_bytes, out_bytes) < 0
                || add_to(lc, s_tx_frames, m) < 0 || add_to(lc, s_tx_bytes, out_bytes) < 0)
                return NULL;
            pending = 1;
        }
        PyObject *done = PyObject_CallNoArgs(release);
        if (done == NULL)
            return NULL;
        Py_DECREF(done);
    }
}
#endif

static PyMethodDef methods[] = {
    {"route", (PyCFunction)(void (*)(void))route, METH_FASTCALL,
     "route(datagrams, start, info, seen, seen_at, own, last_seq, now, boxes, boxes_of, "
     "dests, dests_of, link) -> (stop, frames, bytes, forwarded, mailboxed, lost)\n\n"
     "Route the datagrams from index start on while each takes the router's common path; "
     "see backends/mavlink/router.py (Router._route_datagrams)."},
#ifdef __linux__
    {"lane", (PyCFunction)(void (*)(void))lane, METH_FASTCALL,
     "lane(...) -> (reason, ...): a UDP route's wake-ups in one call; see "
     "backends/mavlink/lane.py."},
#endif
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module_def = {
    PyModuleDef_HEAD_INIT, "_route_speedups",
    "The MAVLink router's common case, compiled (the pure-Python path is the reference).",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__route_speedups(void)
{
#ifdef __linux__
    if (intern_names() < 0)
        return NULL;
#endif
    return PyModule_Create(&module_def);
}
