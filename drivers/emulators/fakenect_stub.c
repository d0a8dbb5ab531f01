/* fieldguard: a tiny library preloaded (LD_PRELOAD) beside libfreenect's "fakenect" playback
 * library (Debian 12: libfreenect-bin 0.5.3, /usr/lib/<triplet>/fakenect/libfreenect.so) so that
 * the real Python binding and libfreenect_sync run against a recorded dump.
 *
 * It fills two gaps of Debian's fakenect, nothing else:
 *  1. freenect_camera_to_world: libfreenect_sync.so links against it, fakenect does not define
 *     it, so the binding cannot even be loaded. Nobody calls it here; it computes what
 *     libfreenect's registration.c does, with the Kinect's typical zero-plane constants.
 *  2. freenect_find_depth_mode: fakenect 0.5.3 asserts the 11-bit mode (abort() on anything
 *     else). This version returns libfreenect's own descriptors for 11/10-bit, registered and mm
 *     depth (all 640x480 x 16 bit). fakenect copies the dump's 16-bit frame through unchanged
 *     whatever the mode, so a dump written with registered depth in millimetres plays back as a
 *     Kinect in FREENECT_DEPTH_REGISTERED mode delivers it.
 * Everything else (INDEX.txt parsing, frame timing, callbacks, the binding) is the real code.
 *
 * Build: gcc -shared -fPIC -O2 -o libfakenect_stub.so fakenect_stub.c
 * (drivers/emulators/fakenect_dump.py: build_stub()).
 */
#include <libfreenect.h>

void freenect_camera_to_world(freenect_device *dev, int cx, int cy, int wz, double *wx,
                              double *wy)
{
	(void)dev;
	const double ref_pix_size = 0.1042, ref_distance = 120.0;   /* mm, typical Kinect */
	double factor = 2 * ref_pix_size * wz / ref_distance;
	*wx = (double)(cx - 320) * factor;
	*wy = (double)(cy - 240) * factor;
}

freenect_frame_mode freenect_find_depth_mode(freenect_resolution res, freenect_depth_format fmt)
{
	freenect_frame_mode m = {0};
	int bits;
	if (res != FREENECT_RESOLUTION_MEDIUM)
		return m;                                   /* is_valid = 0 */
	switch (fmt) {
	case FREENECT_DEPTH_11BIT: bits = 11; break;
	case FREENECT_DEPTH_10BIT: bits = 10; break;
	case FREENECT_DEPTH_REGISTERED:
	case FREENECT_DEPTH_MM: bits = 16; break;
	default: return m;                              /* packed formats: not in a dump */
	}
	m.reserved = ((uint32_t)(res & 0xff) << 8) | (uint32_t)(fmt & 0xff);
	m.resolution = res;
	m.depth_format = fmt;
	m.bytes = 640 * 480 * 2;
	m.width = 640;
	m.height = 480;
	m.data_bits_per_pixel = (int8_t)bits;
	m.padding_bits_per_pixel = (int8_t)(16 - bits);
	m.framerate = 30;
	m.is_valid = 1;
	return m;
}
