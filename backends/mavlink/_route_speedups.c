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

static PyMethodDef methods[] = {
    {"route", (PyCFunction)(void (*)(void))route, METH_FASTCALL,
     "route(datagrams, start, info, seen, seen_at, own, last_seq, now, boxes, boxes_of, "
     "dests, dests_of, link) -> (stop, frames, bytes, forwarded, mailboxed, lost)\n\n"
     "Route the datagrams from index start on while each takes the router's common path; "
     "see backends/mavlink/router.py (Router._route_datagrams)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module_def = {
    PyModuleDef_HEAD_INIT, "_route_speedups",
    "The MAVLink router's common case, compiled (the pure-Python path is the reference).",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__route_speedups(void)
{
    return PyModule_Create(&module_def);
}
