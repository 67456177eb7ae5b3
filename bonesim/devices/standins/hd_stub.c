/* A stand-in for the OpenHaptics HD library (libHD.so): the functions the
 * pyOpenHaptics binding calls, over a simulated Touch-class arm.
 *
 * The scheduler runs the scheduled callbacks on its own thread every
 * millisecond, as the real library's servo loop does. Between frames the
 * stylus (a point mass held by a passive hand: mass, damping and a spring to
 * where the hand rests) moves under the force last set in a frame. Test
 * controls (stub_*) place the hand, unplug the arm (every call then reports
 * HD_COMM_ERROR and hdInitDevice fails) and read back what was rendered.
 * Units as the HD library's: mm, N, N/mm, seconds.
 */
#include <math.h>
#include <pthread.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

typedef unsigned int HHD;
typedef unsigned int HDenum;
typedef unsigned int HDerror;
typedef unsigned int HDCallbackCode;
typedef HDCallbackCode (*HDSchedulerCallback)(void *);
typedef struct { HDerror errorCode; int internalErrorCode; HHD hHD; } HDErrorInfo;

#define HD_SUCCESS 0x000
#define HD_INVALID_ENUM 0x0100
#define HD_BAD_HANDLE 0x0104
#define HD_COMM_ERROR 0x0302
#define HD_INVALID_HANDLE 0xFFFFFFFFu
#define HD_CALLBACK_DONE 0
#define HD_CURRENT_BUTTONS 0x2000
#define HD_CURRENT_POSITION 0x2050
#define HD_CURRENT_TRANSFORM 0x2052
#define HD_DEVICE_MODEL_TYPE 0x2501
#define HD_DEVICE_VENDOR 0x2503
#define HD_MAX_WORKSPACE_DIMENSIONS 0x2550
#define HD_USABLE_WORKSPACE_DIMENSIONS 0x2551
#define HD_NOMINAL_MAX_STIFFNESS 0x2602
#define HD_NOMINAL_MAX_FORCE 0x2603
#define HD_NOMINAL_MAX_CONTINUOUS_FORCE 0x2604
#define HD_CURRENT_FORCE 0x2700
#define HD_FORCE_OUTPUT 0x4000

#define MAX_CALLBACKS 8

static pthread_mutex_t mu = PTHREAD_MUTEX_INITIALIZER;
static pthread_t servo;
static volatile int running = 0;
static int unplugged = 0, initialized = 0, force_enabled = 0, in_frame = 0;
static HDErrorInfo last_error = {HD_SUCCESS, 0, 0};
static HDSchedulerCallback callbacks[MAX_CALLBACKS];
static void *callback_data[MAX_CALLBACKS];
static int n_callbacks = 0;
static double pos[3] = {0, 0, 0}, vel[3] = {0, 0, 0}, rest[3] = {0, 0, 0};
static double frame_force[3] = {0, 0, 0}, rendered[3] = {0, 0, 0};
static int buttons = 0;
static long frames = 0;
/* a Touch: 3.3 N peak, 0.88 N continuous, 0.39 N/mm, 160 x 120 x 70 mm */
static const double max_force = 3.3, max_cont_force = 0.88, max_stiffness = 0.39;
static const double workspace[6] = {-80, -60, -35, 80, 60, 35};
static const double mass_kg = 0.15, damping = 0.008, spring = 0.02;

static void error(HDerror code) { last_error.errorCode = code; last_error.hHD = 0; }

static void step_arm(double dt) {
    for (int a = 0; a < 3; a++) {
        double f = rendered[a] - damping * vel[a] - spring * (pos[a] - rest[a]);
        vel[a] += dt * 1000.0 / mass_kg * f;
        pos[a] += dt * vel[a];
    }
}

static void *servo_loop(void *arg) {
    (void)arg;
    struct timespec ts = {0, 1000000};
    while (running) {
        pthread_mutex_lock(&mu);
        int n = n_callbacks;
        HDSchedulerCallback cbs[MAX_CALLBACKS];
        void *data[MAX_CALLBACKS];
        memcpy(cbs, callbacks, sizeof(cbs));
        memcpy(data, callback_data, sizeof(data));
        pthread_mutex_unlock(&mu);
        for (int i = 0; i < n; i++) {
            if (cbs[i] && cbs[i](data[i]) == HD_CALLBACK_DONE) {
                pthread_mutex_lock(&mu);
                callbacks[i] = 0;
                pthread_mutex_unlock(&mu);
            }
        }
        pthread_mutex_lock(&mu);
        step_arm(0.001);
        pthread_mutex_unlock(&mu);
        nanosleep(&ts, 0);
    }
    return 0;
}

HHD hdInitDevice(const char *name) {
    (void)name;
    if (unplugged) { error(HD_COMM_ERROR); return HD_INVALID_HANDLE; }
    initialized = 1;
    return 1;
}
void hdDisableDevice(HHD h) { (void)h; initialized = 0; }
HHD hdGetCurrentDevice(void) { return initialized ? 1 : HD_INVALID_HANDLE; }
HDErrorInfo hdGetError(void) {
    HDErrorInfo e = last_error;
    if (unplugged) { e.errorCode = HD_COMM_ERROR; }
    last_error.errorCode = HD_SUCCESS;
    return e;
}
void hdEnable(HDenum cap) { if (cap == HD_FORCE_OUTPUT) force_enabled = 1; }
void hdStartScheduler(void) {
    if (running) return;
    running = 1;
    pthread_create(&servo, 0, servo_loop, 0);
}
void hdStopScheduler(void) {
    if (!running) return;
    running = 0;
    pthread_join(servo, 0);
    pthread_mutex_lock(&mu);
    n_callbacks = 0;
    rendered[0] = rendered[1] = rendered[2] = 0;
    pthread_mutex_unlock(&mu);
}
unsigned long hdScheduleAsynchronous(HDSchedulerCallback cb, void *data, unsigned short prio) {
    (void)prio;
    pthread_mutex_lock(&mu);
    if (n_callbacks < MAX_CALLBACKS) {
        callbacks[n_callbacks] = cb;
        callback_data[n_callbacks] = data;
        n_callbacks++;
    }
    pthread_mutex_unlock(&mu);
    return (unsigned long)n_callbacks;
}
void hdScheduleSynchronous(HDSchedulerCallback cb, void *data, unsigned short prio) {
    (void)prio;
    cb(data);
}
void hdBeginFrame(HHD h) {
    (void)h;
    if (unplugged) { error(HD_COMM_ERROR); return; }
    in_frame = 1;
}
void hdEndFrame(HHD h) {
    (void)h;
    if (unplugged) { error(HD_COMM_ERROR); in_frame = 0; return; }
    pthread_mutex_lock(&mu);
    for (int a = 0; a < 3; a++) rendered[a] = force_enabled ? frame_force[a] : 0.0;
    frames++;
    pthread_mutex_unlock(&mu);
    in_frame = 0;
}
void hdGetDoublev(HDenum what, double *out) {
    if (unplugged) { error(HD_COMM_ERROR); return; }
    pthread_mutex_lock(&mu);
    switch (what) {
    case HD_CURRENT_POSITION: memcpy(out, pos, 3 * sizeof(double)); break;
    case HD_CURRENT_TRANSFORM:   /* column-major; the stylus points along -z (no rotation) */
        memset(out, 0, 16 * sizeof(double));
        out[0] = out[5] = out[10] = out[15] = 1.0;
        out[12] = pos[0]; out[13] = pos[1]; out[14] = pos[2];
        break;
    case HD_CURRENT_FORCE: memcpy(out, rendered, 3 * sizeof(double)); break;
    case HD_MAX_WORKSPACE_DIMENSIONS:
    case HD_USABLE_WORKSPACE_DIMENSIONS: memcpy(out, workspace, 6 * sizeof(double)); break;
    case HD_NOMINAL_MAX_STIFFNESS: out[0] = max_stiffness; break;
    case HD_NOMINAL_MAX_FORCE: out[0] = max_force; break;
    case HD_NOMINAL_MAX_CONTINUOUS_FORCE: out[0] = max_cont_force; break;
    default: error(HD_INVALID_ENUM);
    }
    pthread_mutex_unlock(&mu);
}
void hdGetIntegerv(HDenum what, int *out) {
    if (unplugged) { error(HD_COMM_ERROR); return; }
    if (what == HD_CURRENT_BUTTONS) out[0] = buttons; else error(HD_INVALID_ENUM);
}
void hdSetDoublev(HDenum what, const double *v) {
    if (unplugged) { error(HD_COMM_ERROR); return; }
    if (what != HD_CURRENT_FORCE) { error(HD_INVALID_ENUM); return; }
    pthread_mutex_lock(&mu);
    memcpy(frame_force, v, 3 * sizeof(double));
    pthread_mutex_unlock(&mu);
}
const char *hdGetString(HDenum what) {
    if (what == HD_DEVICE_MODEL_TYPE) return "Touch (stub)";
    if (what == HD_DEVICE_VENDOR) return "3D Systems (stub)";
    error(HD_INVALID_ENUM);
    return "";
}

/* ----- test controls ----- */
void stub_place(double x, double y, double z) {
    pthread_mutex_lock(&mu);
    rest[0] = pos[0] = x; rest[1] = pos[1] = y; rest[2] = pos[2] = z;
    vel[0] = vel[1] = vel[2] = 0;
    pthread_mutex_unlock(&mu);
}
void stub_unplug(int gone) { unplugged = gone; }
void stub_set_buttons(int b) { buttons = b; }
void stub_rendered(double *out) {
    pthread_mutex_lock(&mu);
    memcpy(out, rendered, 3 * sizeof(double));
    pthread_mutex_unlock(&mu);
}
void stub_position(double *out) {
    pthread_mutex_lock(&mu);
    memcpy(out, pos, 3 * sizeof(double));
    pthread_mutex_unlock(&mu);
}
long stub_frames(void) { return frames; }
int stub_running(void) { return running; }
