/* recvmmsg/sendmmsg's per-datagram work, compiled: see gateway/io/mmsg.py.
 *
 * MmsgSocket sets up its message headers once (through ctypes: each receive header points
 * at a slot of its buffer, each send header at an iovec of its own) and passes their
 * address here.  The two calls below do what its pure-Python path does per datagram — the
 * list of bytes made from what recvmmsg wrote, the iovecs pointed at the bytes to write —
 * with the system call made with the GIL released.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#ifdef __linux__  /* (Python.h defines _GNU_SOURCE: recvmmsg and sendmmsg are declared) */
#include <errno.h>
#include <string.h>
#include <sys/socket.h>

/* The senders of datagrams [0, n): the raw sockaddr of each run of consecutive datagrams
 * from one sender, in order (a list of bytes; NULL: error). */
static PyObject *sender_runs(struct mmsghdr *hdrs, int n)
{
    PyObject *runs = PyList_New(0);
    const void *prev = NULL;
    socklen_t prev_len = 0;
    for (int i = 0; runs != NULL && i < n; i++) {
        const void *name = hdrs[i].msg_hdr.msg_name;
        socklen_t len = hdrs[i].msg_hdr.msg_namelen;
        if (prev != NULL && len == prev_len && memcmp(name, prev, len) == 0)
            continue;
        PyObject *raw = PyBytes_FromStringAndSize((const char *)name, (Py_ssize_t)len);
        if (raw == NULL || PyList_Append(runs, raw) < 0)
            Py_CLEAR(runs);
        Py_XDECREF(raw);
        prev = name;
        prev_len = len;
    }
    return runs;
}

/* recv(fd, headers, count[, senders]) -> list of bytes (with senders: (list, sender runs)),
 * or -errno (nothing read) */
static PyObject *recv_batch(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    int fd;
    unsigned long long addr;
    unsigned int count;
    int senders = 0;
    if (nargs != 3 && nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "recv() takes 3 or 4 arguments");
        return NULL;
    }
    if (nargs == 4 && (senders = PyObject_IsTrue(args[3])) < 0)
        return NULL;
    fd = (int)PyLong_AsLong(args[0]);
    addr = PyLong_AsUnsignedLongLong(args[1]);
    count = (unsigned int)PyLong_AsUnsignedLong(args[2]);
    if (PyErr_Occurred())
        return NULL;
    struct mmsghdr *hdrs = (struct mmsghdr *)(uintptr_t)addr;
    int n, err = 0;
    Py_BEGIN_ALLOW_THREADS
    n = recvmmsg(fd, hdrs, count, MSG_DONTWAIT, NULL);
    if (n < 0)
        err = errno;
    Py_END_ALLOW_THREADS
    if (n < 0)
        return PyLong_FromLong(-err);
    PyObject *out = PyList_New(n);
    if (out == NULL)
        return NULL;
    for (int i = 0; i < n; i++) {
        size_t len = hdrs[i].msg_len;
        struct iovec *iov = hdrs[i].msg_hdr.msg_iov;
        if (len > iov->iov_len)  /* cannot happen: recvmmsg writes at most the slot */
            len = iov->iov_len;
        PyObject *b = PyBytes_FromStringAndSize((const char *)iov->iov_base, (Py_ssize_t)len);
        if (b == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyList_SET_ITEM(out, i, b);
    }
    if (!senders)
        return out;
    PyObject *runs = sender_runs(hdrs, n);
    if (runs == NULL) {
        Py_DECREF(out);
        return NULL;
    }
    PyObject *both = PyTuple_Pack(2, out, runs);
    Py_DECREF(out);
    Py_DECREF(runs);
    return both;
}

/* send(fd, headers, count, datagrams, start) -> datagrams written, or -errno.  Writes
 * datagrams[start:start + count] (fewer at the list's end); what is not bytes (a bytearray, a
 * memoryview) is copied to bytes first. */
static PyObject *send_batch(PyObject *module, PyObject *const *args, Py_ssize_t nargs)
{
    (void)module;
    if (nargs != 5) {
        PyErr_SetString(PyExc_TypeError, "send() takes 5 arguments");
        return NULL;
    }
    int fd = (int)PyLong_AsLong(args[0]);
    unsigned long long addr = PyLong_AsUnsignedLongLong(args[1]);
    Py_ssize_t count = PyLong_AsSsize_t(args[2]);
    PyObject *datagrams = args[3];
    Py_ssize_t start = PyLong_AsSsize_t(args[4]);
    if (PyErr_Occurred())
        return NULL;
    if (!PyList_Check(datagrams) || start < 0 || count < 0) {
        PyErr_SetString(PyExc_TypeError, "send(): a list and a start index >= 0");
        return NULL;
    }
    Py_ssize_t total = PyList_GET_SIZE(datagrams);
    Py_ssize_t k = total - start;
    if (k > count)
        k = count;
    if (k <= 0)
        return PyLong_FromLong(0);
    struct mmsghdr *hdrs = (struct mmsghdr *)(uintptr_t)addr;
    /* held while the GIL is released: another thread may change the list meanwhile */
    PyObject **held = PyMem_Malloc((size_t)k * sizeof(PyObject *));
    if (held == NULL)
        return PyErr_NoMemory();
    for (Py_ssize_t i = 0; i < k; i++) {
        PyObject *d = PyList_GET_ITEM(datagrams, start + i);
        d = PyBytes_CheckExact(d) ? Py_NewRef(d) : PyBytes_FromObject(d);  /* a copy */
        if (d == NULL) {
            for (Py_ssize_t j = 0; j < i; j++)
                Py_DECREF(held[j]);
            PyMem_Free(held);
            return NULL;
        }
        held[i] = d;
        struct iovec *iov = hdrs[i].msg_hdr.msg_iov;
        iov->iov_base = PyBytes_AS_STRING(d);
        iov->iov_len = (size_t)PyBytes_GET_SIZE(d);
    }
    int n, err = 0;
    Py_BEGIN_ALLOW_THREADS
    n = sendmmsg(fd, hdrs, (unsigned int)k, MSG_DONTWAIT);
    if (n < 0)
        err = errno;
    Py_END_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < k; i++)
        Py_DECREF(held[i]);
    PyMem_Free(held);
    return PyLong_FromLong(n < 0 ? -err : n);
}

static PyMethodDef methods[] = {
    {"recv", (PyCFunction)(void (*)(void))recv_batch, METH_FASTCALL,
     "recv(fd, headers, count[, senders]) -> list[bytes] | (list[bytes], list[bytes]) | "
     "-errno: one recvmmsg (MSG_DONTWAIT) into the headers at address `headers`, what it read "
     "as bytes; with senders, also the raw sockaddr of each run of datagrams from one sender."},
    {"send", (PyCFunction)(void (*)(void))send_batch, METH_FASTCALL,
     "send(fd, headers, count, datagrams, start) -> written | -errno: one sendmmsg "
     "(MSG_DONTWAIT) of datagrams[start:start + count], the headers' iovecs pointed at them."},
    {NULL, NULL, 0, NULL},
};
#else
static PyMethodDef methods[] = {{NULL, NULL, 0, NULL}};
#endif

static struct PyModuleDef module_def = {
    PyModuleDef_HEAD_INIT, "_mmsg_speedups",
    "recvmmsg/sendmmsg's per-datagram work, compiled (Linux; gateway/io/mmsg.py).",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__mmsg_speedups(void)
{
    return PyModule_Create(&module_def);
}
