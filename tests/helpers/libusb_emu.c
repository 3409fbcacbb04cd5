/*
 * An emulated libusb-1.0 for tests: the subset of the libusb-1.0 ABI that pyusb's libusb1 backend and
 * davis_rig's transfer ring (davis_rig/usb/async_bulk.py) call, playing DAVIS346 cameras (FX3: endpoint 0x82 bulk
 * IN, 0x81 interrupt IN) whose device model lives in the host program and is reached through one callback
 * (emu_set_host). Built at test time by tests/usb/libusb_emu/libusb_emu.py and loaded with
 * usb.backend.libusb1.get_backend(find_library=...), so the unmodified pyusb backend and the unmodified ring run on it.
 *
 * What this file owns is libusb's semantics:
 *   - transfer lifetimes: alloc / submit / cancel / free; a submitted transfer completes exactly once, and its
 *     callback runs in a thread that handles events (libusb_handle_events_timeout_completed, or a synchronous
 *     transfer that finds the event lock free, as libusb_control_transfer does), one callback at a time, with the
 *     transfer's status and actual_length set;
 *   - per-endpoint device threads that fill the oldest submitted transfer from the host's device model (polling it
 *     with a short timeout so a cancel takes effect), and map its answer to a status: data -> COMPLETED,
 *     PIPE -> STALL, NO_DEVICE -> NO_DEVICE (and every other transfer of the device too), TIMEOUT -> still in flight
 *     (TIMED_OUT once the transfer's own timeout, if any, has passed), anything else -> ERROR;
 *   - cancellation racing with completion: a cancel of a queued transfer completes it CANCELLED; of a transfer the
 *     device is filling, CANCELLED with the bytes already received; of a completed but not yet reaped transfer,
 *     LIBUSB_ERROR_NOT_FOUND and the transfer still comes back COMPLETED;
 *   - fault knobs per device (emu_set_faults): completions reaped only after a delay (late completion),
 *     cancellations completed after a delay, every n-th cancel losing the race against a completion (the device
 *     gets one last look for data and the transfer comes back COMPLETED with it), the device poll period;
 *     emu_unplug() for a disconnect at any moment.
 *   - a racing cancel (every n-th, by emu_set_faults) leaves the transfer with the device for one more poll: if data
 *     comes in that poll, the transfer comes back COMPLETED with it, as when a URB completes while being cancelled.
 *
 * It never releases a transfer's memory (freed transfers are kept, marked freed), so it can COUNT misuse instead of
 * crashing on it: a submit / cancel of a freed transfer (use after free), a double free, a free of a transfer still
 * in flight, a submit of a transfer in flight, a libusb_close with transfers in flight, unknown pointers
 * (emu_counter / emu_counter_name).
 */
#define _GNU_SOURCE
#include <pthread.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/time.h>
#include <time.h>

#define EXPORT __attribute__((visibility("default")))

/* ---- libusb.h (ABI of libusb 1.0) ------------------------------------------------------------------------------ */
enum {
    LIBUSB_SUCCESS = 0,
    LIBUSB_ERROR_IO = -1,
    LIBUSB_ERROR_INVALID_PARAM = -2,
    LIBUSB_ERROR_ACCESS = -3,
    LIBUSB_ERROR_NO_DEVICE = -4,
    LIBUSB_ERROR_NOT_FOUND = -5,
    LIBUSB_ERROR_BUSY = -6,
    LIBUSB_ERROR_TIMEOUT = -7,
    LIBUSB_ERROR_OVERFLOW = -8,
    LIBUSB_ERROR_PIPE = -9,
    LIBUSB_ERROR_INTERRUPTED = -10,
    LIBUSB_ERROR_NO_MEM = -11,
    LIBUSB_ERROR_NOT_SUPPORTED = -12,
    LIBUSB_ERROR_OTHER = -99,
};
enum {
    LIBUSB_TRANSFER_COMPLETED = 0,
    LIBUSB_TRANSFER_ERROR = 1,
    LIBUSB_TRANSFER_TIMED_OUT = 2,
    LIBUSB_TRANSFER_CANCELLED = 3,
    LIBUSB_TRANSFER_STALL = 4,
    LIBUSB_TRANSFER_NO_DEVICE = 5,
    LIBUSB_TRANSFER_OVERFLOW = 6,
};
enum { LIBUSB_TRANSFER_TYPE_BULK = 2, LIBUSB_TRANSFER_TYPE_INTERRUPT = 3 };
enum { LIBUSB_SPEED_SUPER = 4 };

struct libusb_device_descriptor {
    uint8_t bLength, bDescriptorType;
    uint16_t bcdUSB;
    uint8_t bDeviceClass, bDeviceSubClass, bDeviceProtocol, bMaxPacketSize0;
    uint16_t idVendor, idProduct, bcdDevice;
    uint8_t iManufacturer, iProduct, iSerialNumber, bNumConfigurations;
};
struct libusb_endpoint_descriptor {
    uint8_t bLength, bDescriptorType, bEndpointAddress, bmAttributes;
    uint16_t wMaxPacketSize;
    uint8_t bInterval, bRefresh, bSynchAddress;
    const unsigned char *extra;
    int extra_length;
};
struct libusb_interface_descriptor {
    uint8_t bLength, bDescriptorType, bInterfaceNumber, bAlternateSetting, bNumEndpoints, bInterfaceClass,
        bInterfaceSubClass, bInterfaceProtocol, iInterface;
    const struct libusb_endpoint_descriptor *endpoint;
    const unsigned char *extra;
    int extra_length;
};
struct libusb_interface {
    const struct libusb_interface_descriptor *altsetting;
    int num_altsetting;
};
struct libusb_config_descriptor {
    uint8_t bLength, bDescriptorType;
    uint16_t wTotalLength;
    uint8_t bNumInterfaces, bConfigurationValue, iConfiguration, bmAttributes, MaxPower;
    const struct libusb_interface *interface;
    const unsigned char *extra;
    int extra_length;
};
struct libusb_iso_packet_descriptor {
    unsigned int length, actual_length;
    int status;
};
struct libusb_transfer;
typedef void (*libusb_transfer_cb_fn)(struct libusb_transfer *);
struct libusb_transfer {
    void *dev_handle;
    uint8_t flags, endpoint, type;
    unsigned int timeout;
    int status, length, actual_length;
    libusb_transfer_cb_fn callback;
    void *user_data;
    unsigned char *buffer;
    int num_iso_packets;
    struct libusb_iso_packet_descriptor iso_packet_desc[];
};

/* ---- the host's device model ----------------------------------------------------------------------------------- */
/* int host(device, op, a, b, c, d, buffer, length, timeout_ms): >= 0 success (a byte count for transfers),
 * < 0 a LIBUSB_ERROR_* code. Never called with the emulator's lock held. */
typedef int (*emu_host_fn)(int, int, int, int, int, int, unsigned char *, int, unsigned int);
enum {
    EMU_OP_PRESENT = 0,    /* -> 1 plugged in, 0 gone */
    EMU_OP_OPEN = 1,       /* a = handle id */
    EMU_OP_CLOSE = 2,      /* a = handle id */
    EMU_OP_GET_CONFIG = 3, /* a = handle id -> configuration value */
    EMU_OP_SET_CONFIG = 4, /* a = handle id, b = value */
    EMU_OP_CLAIM = 5,      /* a = handle id, b = interface */
    EMU_OP_RELEASE = 6,    /* a = handle id, b = interface */
    EMU_OP_CONTROL = 7,    /* a = handle id, b = bmRequestType | bRequest << 8, c = wValue, d = wIndex */
    EMU_OP_BULK_IN = 8,    /* a = handle id, b = endpoint */
    EMU_OP_INTR_IN = 9,    /* a = handle id, b = endpoint */
    EMU_OP_CLEAR_HALT = 10 /* a = handle id, b = endpoint */
};

/* ---- counters -------------------------------------------------------------------------------------------------- */
enum {
    C_USE_AFTER_FREE, /* submit / cancel of a freed transfer */
    C_UNKNOWN_TRANSFER,
    C_DOUBLE_FREE,
    C_FREE_IN_FLIGHT,
    C_SUBMIT_IN_FLIGHT,
    C_CLOSE_IN_FLIGHT,
    C_BAD_HANDLE,
    C_ALLOCATED,
    C_FREED,
    C_SUBMITS,
    C_CANCELS,
    C_CANCEL_NOT_FOUND,
    C_CANCEL_RACES,
    C_COMPLETIONS,
    C_CALLBACKS,
    C_SYNC_CALLBACKS,
    C_DROPPED_COMPLETIONS, /* completions of transfers freed in flight: no callback */
    C_COUNT
};
static const char *COUNTER_NAMES[C_COUNT] = {
    "use_after_free", "unknown_transfer", "double_free", "free_in_flight", "submit_in_flight", "close_in_flight",
    "bad_handle", "allocated", "freed", "submits", "cancels", "cancel_not_found", "cancel_races", "completions",
    "callbacks", "sync_callbacks", "dropped_completions",
};
static long long g_count[C_COUNT];

/* ---- state ----------------------------------------------------------------------------------------------------- */
enum { ST_IDLE, ST_QUEUED, ST_FILLING, ST_DONE, ST_REAPING, ST_FREED };
#define EMU_MAX_DEVICES 256 /* slots are not reused: a stale device pointer stays recognisable */
#define EMU_ENDPOINTS 2
#define EMU_MAX_HANDLES 4096
#define HANDLE_MAGIC 0x48414e44u

struct emu_device;
struct emu_handle {
    uint32_t magic;
    int id;
    int open;
    struct emu_device *dev;
};
struct itransfer;
struct emu_endpoint {
    struct emu_device *dev;
    uint8_t address, type;
    int op;
    struct itransfer *head, *tail; /* submitted transfers, oldest first */
    pthread_t thread;
    int started;
    unsigned char *staging;
    int staging_size;
};
struct emu_device {
    int id, used, gone, quit;
    struct libusb_device_descriptor desc;
    uint8_t bus, address;
    struct emu_endpoint ep[EMU_ENDPOINTS];
    uint64_t completion_delay_ns, cancel_delay_ns;
    int cancel_race_every, poll_ms;
    long long cancel_count;
};
struct itransfer {
    int state, cancel_requested, race;
    struct emu_endpoint *ep;
    struct emu_handle *handle;
    uint64_t submitted_ns, ready_ns;
    struct itransfer *next;  /* endpoint queue */
    struct itransfer *cnext; /* completion queue */
    struct libusb_transfer pub; /* last: isochronous packet descriptors follow */
};

static pthread_mutex_t g_lock = PTHREAD_MUTEX_INITIALIZER;
static pthread_cond_t g_cond;
static emu_host_fn g_host;
static struct emu_device g_devices[EMU_MAX_DEVICES];
static struct emu_handle *g_handles[EMU_MAX_HANDLES];
static int g_handle_count;
static int g_device_count;
static struct itransfer **g_reg; /* every transfer ever allocated (open addressing on the public pointer) */
static size_t g_reg_cap, g_reg_n;
static struct itransfer *g_cq_head, *g_cq_tail; /* completed, not yet reaped, oldest first */
static int g_handler_active;
static int g_interrupt;
static int g_sync_reaps = 1;

static int present(struct emu_device *dev);

__attribute__((constructor)) static void emu_init(void) {
    pthread_condattr_t attr;
    pthread_condattr_init(&attr);
    pthread_condattr_setclock(&attr, CLOCK_MONOTONIC);
    pthread_cond_init(&g_cond, &attr);
    pthread_condattr_destroy(&attr);
}

static uint64_t now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}

static void wait_until(uint64_t deadline_ns) { /* g_lock held */
    struct timespec ts = {(time_t)(deadline_ns / 1000000000ull), (long)(deadline_ns % 1000000000ull)};
    pthread_cond_timedwait(&g_cond, &g_lock, &ts);
}

static int host(int device, int op, int a, int b, int c, int d, unsigned char *buf, int len, unsigned timeout) {
    emu_host_fn fn = g_host;
    return fn ? fn(device, op, a, b, c, d, buf, len, timeout) : LIBUSB_ERROR_NO_DEVICE;
}

/* ---- registry of transfers ------------------------------------------------------------------------------------- */
static size_t hash_ptr(const void *p) {
    uint64_t x = (uint64_t)(uintptr_t)p;
    x ^= x >> 33;
    x *= 0xff51afd7ed558ccdull;
    x ^= x >> 33;
    return (size_t)x;
}

static void reg_put(struct itransfer **table, size_t cap, struct itransfer *t) {
    size_t i = hash_ptr(&t->pub) & (cap - 1);
    while (table[i]) i = (i + 1) & (cap - 1);
    table[i] = t;
}

static int reg_insert(struct itransfer *t) { /* g_lock held */
    if ((g_reg_n + 1) * 2 > g_reg_cap) {
        size_t cap = g_reg_cap ? g_reg_cap * 2 : 1024;
        struct itransfer **table = calloc(cap, sizeof *table);
        if (!table) return -1;
        for (size_t i = 0; i < g_reg_cap; i++)
            if (g_reg[i]) reg_put(table, cap, g_reg[i]);
        free(g_reg);
        g_reg = table;
        g_reg_cap = cap;
    }
    reg_put(g_reg, g_reg_cap, t);
    g_reg_n++;
    return 0;
}

static struct itransfer *reg_lookup(const struct libusb_transfer *p) { /* g_lock held */
    if (!p || !g_reg_cap) return NULL;
    size_t i = hash_ptr(p) & (g_reg_cap - 1);
    while (g_reg[i]) {
        if (&g_reg[i]->pub == p) return g_reg[i];
        i = (i + 1) & (g_reg_cap - 1);
    }
    return NULL;
}

/* ---- queues ---------------------------------------------------------------------------------------------------- */
static void ep_append(struct emu_endpoint *ep, struct itransfer *t) {
    t->next = NULL;
    if (ep->tail) ep->tail->next = t;
    else ep->head = t;
    ep->tail = t;
}

static void ep_remove(struct emu_endpoint *ep, struct itransfer *t) {
    struct itransfer **link = &ep->head, *prev = NULL;
    while (*link && *link != t) {
        prev = *link;
        link = &(*link)->next;
    }
    if (!*link) return;
    *link = t->next;
    if (ep->tail == t) ep->tail = prev;
    t->next = NULL;
}

static void cq_remove(struct itransfer *t) {
    struct itransfer **link = &g_cq_head, *prev = NULL;
    while (*link && *link != t) {
        prev = *link;
        link = &(*link)->cnext;
    }
    if (!*link) return;
    *link = t->cnext;
    if (g_cq_tail == t) g_cq_tail = prev;
    t->cnext = NULL;
}

/* The device finished with t (already out of its endpoint queue): reapable after delay_ns. */
static void complete_locked(struct itransfer *t, int status, int actual_length, uint64_t delay_ns) {
    t->pub.status = status;
    t->pub.actual_length = actual_length;
    t->state = ST_DONE;
    t->ready_ns = now_ns() + delay_ns;
    t->cnext = NULL;
    if (g_cq_tail) g_cq_tail->cnext = t;
    else g_cq_head = t;
    g_cq_tail = t;
    g_count[C_COMPLETIONS]++;
    pthread_cond_broadcast(&g_cond);
}

/* Every transfer queued on the device (not one being filled) comes back NO_DEVICE. */
static void fail_queued_locked(struct emu_device *dev) {
    for (int e = 0; e < EMU_ENDPOINTS; e++) {
        struct emu_endpoint *ep = &dev->ep[e];
        struct itransfer *t = ep->head, *next;
        for (; t; t = next) {
            next = t->next;
            if (t->state != ST_QUEUED) continue;
            ep_remove(ep, t);
            complete_locked(t, LIBUSB_TRANSFER_NO_DEVICE, 0, dev->completion_delay_ns);
        }
    }
}

/* ---- device threads -------------------------------------------------------------------------------------------- */
static int status_of_error(int rc) {
    switch (rc) {
    case LIBUSB_ERROR_PIPE: return LIBUSB_TRANSFER_STALL;
    case LIBUSB_ERROR_NO_DEVICE: return LIBUSB_TRANSFER_NO_DEVICE;
    case LIBUSB_ERROR_OVERFLOW: return LIBUSB_TRANSFER_OVERFLOW;
    default: return LIBUSB_TRANSFER_ERROR;
    }
}

static void *endpoint_main(void *arg) {
    struct emu_endpoint *ep = arg;
    struct emu_device *dev = ep->dev;
    pthread_mutex_lock(&g_lock);
    while (!dev->quit) {
        struct itransfer *t = ep->head;
        if (!t) {
            wait_until(now_ns() + 100000000ull);
            continue;
        }
        if (dev->gone) {
            fail_queued_locked(dev);
            continue;
        }
        if (t->cancel_requested && !t->race) {
            ep_remove(ep, t);
            complete_locked(t, LIBUSB_TRANSFER_CANCELLED, 0, dev->cancel_delay_ns);
            continue;
        }
        int length = t->pub.length > 0 ? t->pub.length : 0;
        if (length > ep->staging_size) {
            unsigned char *staging = realloc(ep->staging, (size_t)length);
            if (!staging) {
                ep_remove(ep, t);
                complete_locked(t, LIBUSB_TRANSFER_ERROR, 0, dev->completion_delay_ns);
                continue;
            }
            ep->staging = staging;
            ep->staging_size = length;
        }
        unsigned timeout = (unsigned)dev->poll_ms; /* for a racing cancel: the device's last look for data */
        int handle_id = t->handle->id;
        t->state = ST_FILLING;
        pthread_mutex_unlock(&g_lock);
        int rc = host(dev->id, ep->op, handle_id, ep->address, 0, 0, ep->staging, length, timeout);
        pthread_mutex_lock(&g_lock);
        ep_remove(ep, t); /* a transfer being filled stays at the head: only this thread takes it out */
        if (t->state == ST_FREED) { /* freed while the device was filling it: its buffer may be gone */
            g_count[C_DROPPED_COMPLETIONS]++;
            continue;
        }
        if (rc >= 0) {
            int n = rc < length ? rc : length;
            memcpy(t->pub.buffer, ep->staging, (size_t)n);
            if (!t->cancel_requested) {
                complete_locked(t, LIBUSB_TRANSFER_COMPLETED, n, dev->completion_delay_ns);
            } else if (t->race && n > 0) {
                g_count[C_CANCEL_RACES]++;
                complete_locked(t, LIBUSB_TRANSFER_COMPLETED, n, dev->completion_delay_ns);
            } else {
                complete_locked(t, LIBUSB_TRANSFER_CANCELLED, n, dev->cancel_delay_ns);
            }
        } else if (rc == LIBUSB_ERROR_TIMEOUT) {
            uint64_t limit = (uint64_t)t->pub.timeout * 1000000ull;
            if (t->cancel_requested) {
                complete_locked(t, LIBUSB_TRANSFER_CANCELLED, 0, dev->cancel_delay_ns);
            } else if (limit && now_ns() - t->submitted_ns >= limit) {
                complete_locked(t, LIBUSB_TRANSFER_TIMED_OUT, 0, dev->completion_delay_ns);
            } else { /* nothing yet: back to the head of the queue, still in flight */
                t->state = ST_QUEUED;
                t->next = ep->head;
                ep->head = t;
                if (!ep->tail) ep->tail = t;
            }
        } else {
            if (rc == LIBUSB_ERROR_NO_DEVICE) dev->gone = 1;
            complete_locked(t, status_of_error(rc), 0, dev->completion_delay_ns);
        }
    }
    pthread_mutex_unlock(&g_lock);
    return NULL;
}

/* ---- event handling -------------------------------------------------------------------------------------------- */
static struct itransfer *cq_pop_ready(uint64_t now) {
    for (struct itransfer *t = g_cq_head; t; t = t->cnext) {
        if (t->ready_ns <= now) {
            cq_remove(t);
            return t;
        }
    }
    return NULL;
}

static uint64_t cq_earliest(void) {
    uint64_t earliest = UINT64_MAX;
    for (struct itransfer *t = g_cq_head; t; t = t->cnext)
        if (t->ready_ns < earliest) earliest = t->ready_ns;
    return earliest;
}

/* Run the callbacks of every reapable transfer, one at a time, in this thread (g_lock held, released around each). */
static int reap_ready_locked(int from_sync_transfer) {
    int reaped = 0;
    struct itransfer *t;
    while ((t = cq_pop_ready(now_ns())) != NULL) {
        libusb_transfer_cb_fn callback = t->pub.callback;
        t->state = ST_REAPING;
        g_count[C_CALLBACKS]++;
        if (from_sync_transfer) g_count[C_SYNC_CALLBACKS]++;
        pthread_mutex_unlock(&g_lock);
        if (callback) callback(&t->pub);
        pthread_mutex_lock(&g_lock);
        if (t->state == ST_REAPING) t->state = ST_IDLE; /* not resubmitted or freed by its callback */
        reaped++;
        pthread_cond_broadcast(&g_cond);
    }
    return reaped;
}

EXPORT int libusb_handle_events_timeout_completed(void *ctx, struct timeval *tv, int *completed) {
    (void)ctx;
    uint64_t timeout_ns = tv ? (uint64_t)tv->tv_sec * 1000000000ull + (uint64_t)tv->tv_usec * 1000ull : 0;
    uint64_t deadline = now_ns() + timeout_ns;
    pthread_mutex_lock(&g_lock);
    if (g_handler_active) { /* another thread handles events: wait as an event waiter, like libusb */
        if (!(completed && *completed)) wait_until(deadline);
        pthread_mutex_unlock(&g_lock);
        return 0;
    }
    g_handler_active = 1;
    for (;;) {
        if (completed && *completed) break;
        if (reap_ready_locked(0) > 0) break;
        if (g_interrupt) {
            g_interrupt = 0;
            break;
        }
        uint64_t now = now_ns();
        if (now >= deadline) break;
        uint64_t until = cq_earliest();
        wait_until(until < deadline ? until : deadline);
    }
    g_handler_active = 0;
    pthread_cond_broadcast(&g_cond);
    pthread_mutex_unlock(&g_lock);
    return 0;
}

EXPORT int libusb_handle_events_timeout(void *ctx, struct timeval *tv) {
    return libusb_handle_events_timeout_completed(ctx, tv, NULL);
}

EXPORT int libusb_handle_events_completed(void *ctx, int *completed) {
    struct timeval tv = {60, 0};
    return libusb_handle_events_timeout_completed(ctx, &tv, completed);
}

EXPORT int libusb_handle_events(void *ctx) { return libusb_handle_events_completed(ctx, NULL); }

EXPORT void libusb_interrupt_event_handler(void *ctx) {
    (void)ctx;
    pthread_mutex_lock(&g_lock);
    g_interrupt = 1;
    pthread_cond_broadcast(&g_cond);
    pthread_mutex_unlock(&g_lock);
}

/* A synchronous transfer waits for its completion by handling events when the event lock is free (libusb's
 * sync_transfer_wait_for_completion): completions of other transfers then run their callbacks in this thread. */
static void sync_handle_events(void) {
    pthread_mutex_lock(&g_lock);
    if (g_sync_reaps && !g_handler_active) {
        g_handler_active = 1;
        reap_ready_locked(1);
        g_handler_active = 0;
        pthread_cond_broadcast(&g_cond);
    }
    pthread_mutex_unlock(&g_lock);
}

/* ---- asynchronous transfers ------------------------------------------------------------------------------------ */
EXPORT struct libusb_transfer *libusb_alloc_transfer(int iso_packets) {
    if (iso_packets < 0) return NULL;
    size_t size = sizeof(struct itransfer) + (size_t)(iso_packets + 1) * sizeof(struct libusb_iso_packet_descriptor);
    struct itransfer *t = calloc(1, size);
    if (!t) return NULL;
    t->state = ST_IDLE;
    t->pub.num_iso_packets = iso_packets;
    pthread_mutex_lock(&g_lock);
    int rc = reg_insert(t);
    if (rc == 0) g_count[C_ALLOCATED]++;
    pthread_mutex_unlock(&g_lock);
    if (rc != 0) {
        free(t);
        return NULL;
    }
    return &t->pub;
}

EXPORT void libusb_free_transfer(struct libusb_transfer *transfer) {
    if (!transfer) return;
    pthread_mutex_lock(&g_lock);
    struct itransfer *t = reg_lookup(transfer);
    if (!t) {
        g_count[C_UNKNOWN_TRANSFER]++;
    } else if (t->state == ST_FREED) {
        g_count[C_DOUBLE_FREE]++;
    } else {
        if (t->state == ST_QUEUED || t->state == ST_FILLING || t->state == ST_DONE) {
            g_count[C_FREE_IN_FLIGHT]++;
            if (t->state == ST_QUEUED) ep_remove(t->ep, t);
            if (t->state == ST_DONE) {
                cq_remove(t);
                g_count[C_DROPPED_COMPLETIONS]++;
            }
        }
        t->state = ST_FREED; /* the memory is kept: later calls on it are counted, not crashed on */
        g_count[C_FREED]++;
        pthread_cond_broadcast(&g_cond);
    }
    pthread_mutex_unlock(&g_lock);
}

static struct emu_handle *handle_of(void *p) { /* a pointer handed out by libusb_open, or NULL */
    for (int i = 0; i < g_handle_count; i++)
        if (g_handles[i] == p) return g_handles[i];
    return NULL;
}

static struct emu_endpoint *endpoint_of(struct emu_device *dev, uint8_t address, uint8_t type) {
    for (int e = 0; e < EMU_ENDPOINTS; e++)
        if (dev->ep[e].address == address && dev->ep[e].type == type) return &dev->ep[e];
    return NULL;
}

EXPORT int libusb_submit_transfer(struct libusb_transfer *transfer) {
    int rc = LIBUSB_SUCCESS;
    pthread_mutex_lock(&g_lock);
    struct itransfer *known = reg_lookup(transfer);
    struct emu_handle *target = known && known->state != ST_FREED ? handle_of(transfer->dev_handle) : NULL;
    pthread_mutex_unlock(&g_lock);
    if (target && target->dev->used) present(target->dev); /* an unplugged device refuses submissions at once */
    pthread_mutex_lock(&g_lock);
    struct itransfer *t = reg_lookup(transfer);
    if (!t) {
        g_count[C_UNKNOWN_TRANSFER]++;
        rc = LIBUSB_ERROR_INVALID_PARAM;
    } else if (t->state == ST_FREED) {
        g_count[C_USE_AFTER_FREE]++;
        rc = LIBUSB_ERROR_NOT_FOUND;
    } else if (t->state == ST_QUEUED || t->state == ST_FILLING || t->state == ST_DONE) {
        g_count[C_SUBMIT_IN_FLIGHT]++;
        rc = LIBUSB_ERROR_BUSY;
    } else {
        struct emu_handle *h = handle_of(transfer->dev_handle);
        struct emu_endpoint *ep = h ? endpoint_of(h->dev, transfer->endpoint, transfer->type) : NULL;
        if (!h || !h->open) {
            g_count[C_BAD_HANDLE]++;
            rc = LIBUSB_ERROR_INVALID_PARAM;
        } else if (h->dev->gone || !h->dev->used) {
            rc = LIBUSB_ERROR_NO_DEVICE;
        } else if (!ep) {
            rc = LIBUSB_ERROR_NOT_FOUND;
        } else {
            t->state = ST_QUEUED;
            t->cancel_requested = t->race = 0;
            t->ep = ep;
            t->handle = h;
            t->submitted_ns = now_ns();
            transfer->status = LIBUSB_TRANSFER_COMPLETED;
            transfer->actual_length = 0;
            ep_append(ep, t);
            g_count[C_SUBMITS]++;
            pthread_cond_broadcast(&g_cond);
        }
    }
    pthread_mutex_unlock(&g_lock);
    return rc;
}

EXPORT int libusb_cancel_transfer(struct libusb_transfer *transfer) {
    int rc = LIBUSB_SUCCESS;
    pthread_mutex_lock(&g_lock);
    struct itransfer *t = reg_lookup(transfer);
    if (!t) {
        g_count[C_UNKNOWN_TRANSFER]++;
        rc = LIBUSB_ERROR_NOT_FOUND;
    } else if (t->state == ST_FREED) {
        g_count[C_USE_AFTER_FREE]++;
        rc = LIBUSB_ERROR_NOT_FOUND;
    } else if ((t->state != ST_QUEUED && t->state != ST_FILLING) || t->cancel_requested) {
        g_count[C_CANCEL_NOT_FOUND]++; /* not in flight, already back (not reaped yet), or already cancelling */
        rc = LIBUSB_ERROR_NOT_FOUND;
    } else {
        struct emu_device *dev = t->ep->dev;
        t->cancel_requested = 1;
        t->race = dev->cancel_race_every > 0 && ++dev->cancel_count % dev->cancel_race_every == 0;
        g_count[C_CANCELS]++;
        if (t->state == ST_QUEUED && !t->race) {
            ep_remove(t->ep, t);
            complete_locked(t, LIBUSB_TRANSFER_CANCELLED, 0, dev->cancel_delay_ns);
        }
        pthread_cond_broadcast(&g_cond);
    }
    pthread_mutex_unlock(&g_lock);
    return rc;
}

/* ---- devices, handles, descriptors ----------------------------------------------------------------------------- */
static struct emu_device *device_of(void *p) {
    for (int i = 0; i < EMU_MAX_DEVICES; i++)
        if (p == &g_devices[i] && g_devices[i].used) return &g_devices[i];
    return NULL;
}

static int present(struct emu_device *dev) {
    if (dev->gone) return 0;
    int rc = host(dev->id, EMU_OP_PRESENT, 0, 0, 0, 0, NULL, 0, 0);
    if (rc <= 0) {
        pthread_mutex_lock(&g_lock);
        dev->gone = 1;
        pthread_cond_broadcast(&g_cond);
        pthread_mutex_unlock(&g_lock);
    }
    return rc > 0;
}

/* A host answer for a device: remember a disconnect. */
static int seen(struct emu_device *dev, int rc) {
    if (rc == LIBUSB_ERROR_NO_DEVICE) {
        pthread_mutex_lock(&g_lock);
        dev->gone = 1;
        pthread_cond_broadcast(&g_cond);
        pthread_mutex_unlock(&g_lock);
    }
    return rc;
}

EXPORT int libusb_init(void **ctx) {
    if (ctx) *ctx = calloc(1, 16);
    return LIBUSB_SUCCESS;
}

EXPORT void libusb_exit(void *ctx) { free(ctx); }

EXPORT void libusb_set_debug(void *ctx, int level) {
    (void)ctx;
    (void)level;
}

EXPORT int libusb_set_option(void *ctx, int option, ...) {
    (void)ctx;
    (void)option;
    return LIBUSB_SUCCESS;
}

EXPORT long libusb_get_device_list(void *ctx, void ***list) {
    (void)ctx;
    void **out = calloc(EMU_MAX_DEVICES + 1, sizeof *out);
    if (!out) return LIBUSB_ERROR_NO_MEM;
    long n = 0;
    for (int i = 0; i < EMU_MAX_DEVICES; i++)
        if (g_devices[i].used && present(&g_devices[i])) out[n++] = &g_devices[i];
    *list = out;
    return n;
}

EXPORT void libusb_free_device_list(void **list, int unref) {
    (void)unref;
    free(list);
}

EXPORT void *libusb_ref_device(void *dev) { return dev; }
EXPORT void libusb_unref_device(void *dev) { (void)dev; }
EXPORT void *libusb_get_parent(void *dev) {
    (void)dev;
    return NULL;
}

EXPORT uint8_t libusb_get_bus_number(void *p) {
    struct emu_device *dev = device_of(p);
    return dev ? dev->bus : 0;
}

EXPORT uint8_t libusb_get_device_address(void *p) {
    struct emu_device *dev = device_of(p);
    return dev ? dev->address : 0;
}

EXPORT int libusb_get_device_speed(void *p) {
    (void)p;
    return LIBUSB_SPEED_SUPER;
}

EXPORT uint8_t libusb_get_port_number(void *p) {
    (void)p;
    return 1;
}

EXPORT int libusb_get_port_numbers(void *p, uint8_t *ports, int length) {
    (void)p;
    if (length < 1) return LIBUSB_ERROR_OVERFLOW;
    ports[0] = 1;
    return 1;
}

EXPORT int libusb_get_device_descriptor(void *p, struct libusb_device_descriptor *desc) {
    struct emu_device *dev = device_of(p);
    if (!dev) return LIBUSB_ERROR_NO_DEVICE;
    *desc = dev->desc;
    return LIBUSB_SUCCESS;
}

struct config_block {
    struct libusb_config_descriptor config;
    struct libusb_interface interface;
    struct libusb_interface_descriptor altsetting;
    struct libusb_endpoint_descriptor endpoints[EMU_ENDPOINTS];
};

EXPORT int libusb_get_config_descriptor(void *p, uint8_t index, struct libusb_config_descriptor **config) {
    struct emu_device *dev = device_of(p);
    if (!dev) return LIBUSB_ERROR_NO_DEVICE;
    if (index != 0) return LIBUSB_ERROR_NOT_FOUND;
    struct config_block *b = calloc(1, sizeof *b);
    if (!b) return LIBUSB_ERROR_NO_MEM;
    for (int e = 0; e < EMU_ENDPOINTS; e++) {
        struct libusb_endpoint_descriptor *d = &b->endpoints[e];
        d->bLength = 7;
        d->bDescriptorType = 5;
        d->bEndpointAddress = dev->ep[e].address;
        d->bmAttributes = dev->ep[e].type;
        d->wMaxPacketSize = dev->ep[e].type == LIBUSB_TRANSFER_TYPE_BULK ? 1024 : 64;
        d->bInterval = dev->ep[e].type == LIBUSB_TRANSFER_TYPE_BULK ? 0 : 4;
    }
    b->altsetting =
        (struct libusb_interface_descriptor){9, 4, 0, 0, EMU_ENDPOINTS, 0xFF, 0, 0, 0, b->endpoints, NULL, 0};
    b->interface = (struct libusb_interface){&b->altsetting, 1};
    b->config = (struct libusb_config_descriptor){9, 2, 9 + 9 + 7 * EMU_ENDPOINTS, 1, 1, 0, 0x80, 112,
                                                  &b->interface, NULL, 0};
    *config = &b->config;
    return LIBUSB_SUCCESS;
}

EXPORT int libusb_get_active_config_descriptor(void *p, struct libusb_config_descriptor **config) {
    return libusb_get_config_descriptor(p, 0, config);
}

EXPORT void libusb_free_config_descriptor(struct libusb_config_descriptor *config) { free(config); }

EXPORT int libusb_get_max_packet_size(void *p, unsigned char endpoint) {
    struct emu_device *dev = device_of(p);
    if (!dev) return LIBUSB_ERROR_NO_DEVICE;
    for (int e = 0; e < EMU_ENDPOINTS; e++)
        if (dev->ep[e].address == endpoint) return dev->ep[e].type == LIBUSB_TRANSFER_TYPE_BULK ? 1024 : 64;
    return LIBUSB_ERROR_NOT_FOUND;
}

EXPORT int libusb_get_max_iso_packet_size(void *p, unsigned char endpoint) {
    return libusb_get_max_packet_size(p, endpoint);
}

EXPORT int libusb_open(void *p, void **handle) {
    struct emu_device *dev = device_of(p);
    if (!dev || !present(dev)) return LIBUSB_ERROR_NO_DEVICE;
    struct emu_handle *h = calloc(1, sizeof *h);
    if (!h) return LIBUSB_ERROR_NO_MEM;
    pthread_mutex_lock(&g_lock);
    if (g_handle_count >= EMU_MAX_HANDLES) {
        pthread_mutex_unlock(&g_lock);
        free(h);
        return LIBUSB_ERROR_NO_MEM;
    }
    *h = (struct emu_handle){HANDLE_MAGIC, g_handle_count, 0, dev};
    g_handles[g_handle_count++] = h; /* handles are never released: a stale one is recognised */
    pthread_mutex_unlock(&g_lock);
    int rc = seen(dev, host(dev->id, EMU_OP_OPEN, h->id, 0, 0, 0, NULL, 0, 0));
    if (rc < 0) return rc;
    pthread_mutex_lock(&g_lock);
    h->open = 1;
    pthread_mutex_unlock(&g_lock);
    *handle = h;
    return LIBUSB_SUCCESS;
}

static struct emu_handle *open_handle(void *p) {
    pthread_mutex_lock(&g_lock);
    struct emu_handle *h = handle_of(p);
    if (!h || !h->open) {
        g_count[C_BAD_HANDLE]++;
        h = NULL;
    }
    pthread_mutex_unlock(&g_lock);
    return h;
}

EXPORT void libusb_close(void *p) {
    struct emu_handle *h = open_handle(p);
    if (!h) return;
    pthread_mutex_lock(&g_lock);
    for (size_t i = 0; i < g_reg_cap; i++) {
        struct itransfer *t = g_reg[i];
        if (t && t->handle == h && (t->state == ST_QUEUED || t->state == ST_FILLING || t->state == ST_DONE))
            g_count[C_CLOSE_IN_FLIGHT]++;
    }
    h->open = 0;
    pthread_mutex_unlock(&g_lock);
    host(h->dev->id, EMU_OP_CLOSE, h->id, 0, 0, 0, NULL, 0, 0);
}

EXPORT int libusb_get_configuration(void *p, int *config) {
    struct emu_handle *h = open_handle(p);
    if (!h) return LIBUSB_ERROR_NO_DEVICE;
    int rc = seen(h->dev, host(h->dev->id, EMU_OP_GET_CONFIG, h->id, 0, 0, 0, NULL, 0, 0));
    if (rc < 0) return rc;
    *config = rc;
    return LIBUSB_SUCCESS;
}

static int handle_op(void *p, int op, int b) {
    struct emu_handle *h = open_handle(p);
    if (!h) return LIBUSB_ERROR_NO_DEVICE;
    int rc = seen(h->dev, host(h->dev->id, op, h->id, b, 0, 0, NULL, 0, 0));
    sync_handle_events();
    return rc < 0 ? rc : LIBUSB_SUCCESS;
}

EXPORT int libusb_set_configuration(void *p, int value) { return handle_op(p, EMU_OP_SET_CONFIG, value); }
EXPORT int libusb_claim_interface(void *p, int interface) { return handle_op(p, EMU_OP_CLAIM, interface); }
EXPORT int libusb_release_interface(void *p, int interface) { return handle_op(p, EMU_OP_RELEASE, interface); }
EXPORT int libusb_clear_halt(void *p, unsigned char endpoint) { return handle_op(p, EMU_OP_CLEAR_HALT, endpoint); }

EXPORT int libusb_set_interface_alt_setting(void *p, int interface, int alternate) {
    struct emu_handle *h = open_handle(p);
    if (!h) return LIBUSB_ERROR_NO_DEVICE;
    if (h->dev->gone) return LIBUSB_ERROR_NO_DEVICE;
    return interface == 0 && alternate == 0 ? LIBUSB_SUCCESS : LIBUSB_ERROR_NOT_FOUND;
}

EXPORT int libusb_reset_device(void *p) {
    struct emu_handle *h = open_handle(p);
    return !h || h->dev->gone ? LIBUSB_ERROR_NO_DEVICE : LIBUSB_SUCCESS;
}

EXPORT int libusb_kernel_driver_active(void *p, int interface) {
    (void)interface;
    return open_handle(p) ? 0 : LIBUSB_ERROR_NO_DEVICE;
}

EXPORT int libusb_detach_kernel_driver(void *p, int interface) {
    (void)interface;
    return open_handle(p) ? LIBUSB_ERROR_NOT_FOUND : LIBUSB_ERROR_NO_DEVICE;
}

EXPORT int libusb_attach_kernel_driver(void *p, int interface) { return libusb_detach_kernel_driver(p, interface); }

/* ---- synchronous transfers ------------------------------------------------------------------------------------- */
EXPORT int libusb_control_transfer(void *p, uint8_t request_type, uint8_t request, uint16_t value, uint16_t index,
                                   unsigned char *data, uint16_t length, unsigned int timeout) {
    struct emu_handle *h = open_handle(p);
    if (!h) return LIBUSB_ERROR_NO_DEVICE;
    if (h->dev->gone) return LIBUSB_ERROR_NO_DEVICE;
    int rc = seen(h->dev, host(h->dev->id, EMU_OP_CONTROL, h->id, request_type | (request << 8), value, index, data,
                               length, timeout));
    sync_handle_events();
    return rc;
}

static int sync_read(void *p, int op, unsigned char endpoint, unsigned char *data, int length, int *transferred,
                     unsigned int timeout) {
    if (transferred) *transferred = 0;
    struct emu_handle *h = open_handle(p);
    if (!h) return LIBUSB_ERROR_NO_DEVICE;
    if (h->dev->gone) return LIBUSB_ERROR_NO_DEVICE;
    if (!(endpoint & 0x80)) return LIBUSB_ERROR_PIPE; /* the DAVIS has no OUT data endpoint */
    int rc = seen(h->dev, host(h->dev->id, op, h->id, endpoint, 0, 0, data, length, timeout));
    sync_handle_events();
    if (rc < 0) return rc;
    if (transferred) *transferred = rc;
    return LIBUSB_SUCCESS;
}

EXPORT int libusb_bulk_transfer(void *p, unsigned char endpoint, unsigned char *data, int length, int *transferred,
                                unsigned int timeout) {
    return sync_read(p, EMU_OP_BULK_IN, endpoint, data, length, transferred, timeout);
}

EXPORT int libusb_interrupt_transfer(void *p, unsigned char endpoint, unsigned char *data, int length,
                                     int *transferred, unsigned int timeout) {
    return sync_read(p, EMU_OP_INTR_IN, endpoint, data, length, transferred, timeout);
}

EXPORT int libusb_get_string_descriptor_ascii(void *p, uint8_t index, unsigned char *data, int length) {
    unsigned char buffer[255];
    int rc = libusb_control_transfer(p, 0x80, 6, 0x0300, 0, buffer, sizeof buffer, 1000);
    if (rc < 4) return rc < 0 ? rc : LIBUSB_ERROR_IO;
    uint16_t langid = (uint16_t)(buffer[2] | buffer[3] << 8);
    rc = libusb_control_transfer(p, 0x80, 6, (uint16_t)(0x0300 | index), langid, buffer, sizeof buffer, 1000);
    if (rc < 2) return rc < 0 ? rc : LIBUSB_ERROR_IO;
    int n = 0;
    for (int i = 2; i + 1 < rc && n < length - 1; i += 2)
        data[n++] = buffer[i + 1] == 0 && buffer[i] < 0x80 ? buffer[i] : '?';
    if (length > 0) data[n] = 0;
    return n;
}

EXPORT const char *libusb_error_name(int code) {
    switch (code) {
    case LIBUSB_SUCCESS: return "LIBUSB_SUCCESS";
    case LIBUSB_ERROR_IO: return "LIBUSB_ERROR_IO";
    case LIBUSB_ERROR_INVALID_PARAM: return "LIBUSB_ERROR_INVALID_PARAM";
    case LIBUSB_ERROR_ACCESS: return "LIBUSB_ERROR_ACCESS";
    case LIBUSB_ERROR_NO_DEVICE: return "LIBUSB_ERROR_NO_DEVICE";
    case LIBUSB_ERROR_NOT_FOUND: return "LIBUSB_ERROR_NOT_FOUND";
    case LIBUSB_ERROR_BUSY: return "LIBUSB_ERROR_BUSY";
    case LIBUSB_ERROR_TIMEOUT: return "LIBUSB_ERROR_TIMEOUT";
    case LIBUSB_ERROR_OVERFLOW: return "LIBUSB_ERROR_OVERFLOW";
    case LIBUSB_ERROR_PIPE: return "LIBUSB_ERROR_PIPE";
    case LIBUSB_ERROR_INTERRUPTED: return "LIBUSB_ERROR_INTERRUPTED";
    case LIBUSB_ERROR_NO_MEM: return "LIBUSB_ERROR_NO_MEM";
    case LIBUSB_ERROR_NOT_SUPPORTED: return "LIBUSB_ERROR_NOT_SUPPORTED";
    default: return "LIBUSB_ERROR_OTHER";
    }
}

EXPORT const char *libusb_strerror(int code) {
    switch (code) {
    case LIBUSB_SUCCESS: return "Success";
    case LIBUSB_ERROR_IO: return "Input/Output Error";
    case LIBUSB_ERROR_INVALID_PARAM: return "Invalid parameter";
    case LIBUSB_ERROR_ACCESS: return "Access denied (insufficient permissions)";
    case LIBUSB_ERROR_NO_DEVICE: return "No such device (it may have been disconnected)";
    case LIBUSB_ERROR_NOT_FOUND: return "Entity not found";
    case LIBUSB_ERROR_BUSY: return "Resource busy";
    case LIBUSB_ERROR_TIMEOUT: return "Operation timed out";
    case LIBUSB_ERROR_OVERFLOW: return "Overflow";
    case LIBUSB_ERROR_PIPE: return "Pipe error";
    case LIBUSB_ERROR_INTERRUPTED: return "System call interrupted (perhaps due to signal)";
    case LIBUSB_ERROR_NO_MEM: return "Insufficient memory";
    case LIBUSB_ERROR_NOT_SUPPORTED: return "Operation not supported or unimplemented on this platform";
    default: return "Other error";
    }
}

/* ---- control of the emulation ---------------------------------------------------------------------------------- */
EXPORT void emu_set_host(emu_host_fn fn) { g_host = fn; }

EXPORT void emu_set_sync_event_handling(int on) { g_sync_reaps = on; }

/* Plug in a DAVIS FX3 (0x82 bulk IN, 0x81 interrupt IN); returns its device number, or -1 when all
 * EMU_MAX_DEVICES numbers of this process are used. */
EXPORT int emu_add_device(int vid, int pid, int bcd_device, int bus, int address, int serial_index) {
    pthread_mutex_lock(&g_lock);
    if (g_device_count >= EMU_MAX_DEVICES) {
        pthread_mutex_unlock(&g_lock);
        return -1;
    }
    int id = g_device_count++;
    struct emu_device *dev = &g_devices[id];
    memset(dev, 0, sizeof *dev);
    dev->id = id;
    dev->used = 1;
    dev->bus = (uint8_t)bus;
    dev->address = (uint8_t)address;
    dev->poll_ms = 10;
    dev->desc = (struct libusb_device_descriptor){18, 1, 0x0300, 0, 0, 0, 9, (uint16_t)vid, (uint16_t)pid,
                                                  (uint16_t)bcd_device, 1, 2, (uint8_t)serial_index, 1};
    const uint8_t addresses[EMU_ENDPOINTS] = {0x82, 0x81};
    const uint8_t types[EMU_ENDPOINTS] = {LIBUSB_TRANSFER_TYPE_BULK, LIBUSB_TRANSFER_TYPE_INTERRUPT};
    for (int e = 0; e < EMU_ENDPOINTS; e++) {
        struct emu_endpoint *ep = &dev->ep[e];
        ep->dev = dev;
        ep->address = addresses[e];
        ep->type = types[e];
        ep->op = types[e] == LIBUSB_TRANSFER_TYPE_BULK ? EMU_OP_BULK_IN : EMU_OP_INTR_IN;
        ep->started = pthread_create(&ep->thread, NULL, endpoint_main, ep) == 0;
    }
    pthread_mutex_unlock(&g_lock);
    return id;
}

EXPORT int emu_set_faults(int id, long completion_delay_us, long cancel_delay_us, int cancel_race_every,
                          int poll_ms) {
    if (id < 0 || id >= EMU_MAX_DEVICES || !g_devices[id].used) return LIBUSB_ERROR_NOT_FOUND;
    pthread_mutex_lock(&g_lock);
    struct emu_device *dev = &g_devices[id];
    dev->completion_delay_ns = (uint64_t)(completion_delay_us > 0 ? completion_delay_us : 0) * 1000ull;
    dev->cancel_delay_ns = (uint64_t)(cancel_delay_us > 0 ? cancel_delay_us : 0) * 1000ull;
    dev->cancel_race_every = cancel_race_every > 0 ? cancel_race_every : 0;
    dev->poll_ms = poll_ms > 0 ? poll_ms : 1;
    pthread_mutex_unlock(&g_lock);
    return LIBUSB_SUCCESS;
}

/* Pull the cable of a device now: its queued transfers come back NO_DEVICE, later calls fail with NO_DEVICE. */
EXPORT void emu_unplug(int id) {
    if (id < 0 || id >= EMU_MAX_DEVICES) return;
    pthread_mutex_lock(&g_lock);
    if (g_devices[id].used) {
        g_devices[id].gone = 1;
        fail_queued_locked(&g_devices[id]);
    }
    pthread_mutex_unlock(&g_lock);
}

/* Unplug every device and stop its threads; returns the transfers still in flight (not reaped) afterwards. */
EXPORT int emu_remove_all(void) {
    for (int i = 0; i < EMU_MAX_DEVICES; i++) {
        struct emu_device *dev = &g_devices[i];
        pthread_mutex_lock(&g_lock);
        if (!dev->used) {
            pthread_mutex_unlock(&g_lock);
            continue;
        }
        dev->gone = 1;
        dev->quit = 1;
        pthread_cond_broadcast(&g_cond);
        pthread_mutex_unlock(&g_lock);
        for (int e = 0; e < EMU_ENDPOINTS; e++)
            if (dev->ep[e].started) pthread_join(dev->ep[e].thread, NULL);
        pthread_mutex_lock(&g_lock);
        fail_queued_locked(dev);
        for (int e = 0; e < EMU_ENDPOINTS; e++) {
            free(dev->ep[e].staging);
            dev->ep[e].staging = NULL;
            dev->ep[e].staging_size = 0;
            dev->ep[e].started = 0;
        }
        dev->used = 0;
        pthread_mutex_unlock(&g_lock);
    }
    pthread_mutex_lock(&g_lock);
    int in_flight = 0;
    for (size_t i = 0; i < g_reg_cap; i++) {
        struct itransfer *t = g_reg[i];
        if (t && (t->state == ST_QUEUED || t->state == ST_FILLING || t->state == ST_DONE)) in_flight++;
    }
    pthread_mutex_unlock(&g_lock);
    return in_flight;
}

/* Transfers submitted and not yet reaped. */
EXPORT int emu_in_flight(void) {
    pthread_mutex_lock(&g_lock);
    int n = 0;
    for (size_t i = 0; i < g_reg_cap; i++) {
        struct itransfer *t = g_reg[i];
        if (t && (t->state == ST_QUEUED || t->state == ST_FILLING || t->state == ST_DONE)) n++;
    }
    pthread_mutex_unlock(&g_lock);
    return n;
}

EXPORT int emu_counter_count(void) { return C_COUNT; }

EXPORT const char *emu_counter_name(int i) { return i >= 0 && i < C_COUNT ? COUNTER_NAMES[i] : NULL; }

EXPORT long long emu_counter(int i) {
    pthread_mutex_lock(&g_lock);
    long long value = i >= 0 && i < C_COUNT ? g_count[i] : 0;
    pthread_mutex_unlock(&g_lock);
    return value;
}

EXPORT void emu_reset_counters(void) {
    pthread_mutex_lock(&g_lock);
    memset(g_count, 0, sizeof g_count);
    pthread_mutex_unlock(&g_lock);
}
