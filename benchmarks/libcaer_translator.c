/*
 * Reference for benchmarks/decode.py: libcaer's own DAVIS event translator (davisCommonEventTranslator in the
 * checkout's src/davis_common.h), compiled unchanged from a user-provided libcaer source checkout and driven
 * without a device.
 *
 * Built by benchmarks/_libcaer.py (nothing of libcaer is kept in this repository): this file includes the
 * checkout's davis_common.h, which holds the whole DAVIS host logic as static functions, and supplies what the
 * USB layer normally does — the SPI configuration calls (the device-info registers of a DAVIS346 answered from a
 * table, sends accepted and ignored) — then opens the handle the way libcaer's davisOpen/caerDeviceDataStart do
 * (settings init, davisCommonInit, davisCommonDataStart), calls the translator once per transfer as libcaer's USB
 * thread does, and drains the packet containers after each transfer as a caerDeviceDataGet consumer would.
 *
 * Entry point (ctypes): lc_run(bytes, n_bytes, transfer_bytes, out) decodes a whole stream with a fresh handle
 * and writes [polarity events, special events, translator nanoseconds (CLOCK_MONOTONIC, summed over the
 * translator calls only)] to out; returns 0, or -1 when libcaer failed to allocate its state.
 */
#include "davis_common.h"

#include <time.h>

/* DAVIS346 device-info registers (PROTOCOL.md section 5): (module, parameter) -> value. */
static uint32_t lcRegister(uint16_t moduleAddr, uint16_t paramAddr) {
	if (moduleAddr == DAVIS_CONFIG_SYSINFO) {
		switch (paramAddr) {
			case DAVIS_CONFIG_SYSINFO_LOGIC_CLOCK:
				return 104;
			case DAVIS_CONFIG_SYSINFO_ADC_CLOCK:
				return 104;
			case DAVIS_CONFIG_SYSINFO_USB_CLOCK:
				return 80;
			case DAVIS_CONFIG_SYSINFO_CLOCK_DEVIATION:
				return 1000;
			default:
				return 0;
		}
	}
	if (moduleAddr == DAVIS_CONFIG_DVS || moduleAddr == DAVIS_CONFIG_APS) {
		switch (paramAddr) {
			case 0: /* SIZE_COLUMNS */
				return 346;
			case 1: /* SIZE_ROWS */
				return 260;
			default: /* ORIENTATION_INFO: no inversion, no flip */
				return 0;
		}
	}
	return 0;
}

static bool spiConfigSendMultiple(void *state, spiConfigParams configs, uint16_t numConfigs) {
	(void) state;
	(void) configs;
	(void) numConfigs;
	return true;
}

static bool spiConfigSendMultipleAsync(void *state, spiConfigParams configs, uint16_t numConfigs,
	void (*configSendCallback)(void *configSendCallbackPtr, int status), void *configSendCallbackPtr) {
	(void) state;
	(void) configs;
	(void) numConfigs;
	(void) configSendCallback;
	(void) configSendCallbackPtr;
	return true;
}

static bool spiConfigSend(void *state, uint16_t moduleAddr, uint16_t paramAddr, uint32_t param) {
	(void) state;
	(void) moduleAddr;
	(void) paramAddr;
	(void) param;
	return true;
}

static bool spiConfigSendAsync(void *state, uint16_t moduleAddr, uint16_t paramAddr, uint32_t param,
	void (*configSendCallback)(void *configSendCallbackPtr, int status), void *configSendCallbackPtr) {
	(void) state;
	(void) moduleAddr;
	(void) paramAddr;
	(void) param;
	(void) configSendCallback;
	(void) configSendCallbackPtr;
	return true;
}

static bool spiConfigReceive(void *state, uint16_t moduleAddr, uint16_t paramAddr, uint32_t *param) {
	(void) state;
	*param = lcRegister(moduleAddr, paramAddr);
	return true;
}

static bool spiConfigReceiveAsync(void *state, uint16_t moduleAddr, uint16_t paramAddr,
	void (*configReceiveCallback)(void *configReceiveCallbackPtr, int status, uint32_t param),
	void *configReceiveCallbackPtr) {
	(void) state;
	(void) moduleAddr;
	(void) paramAddr;
	(void) configReceiveCallback;
	(void) configReceiveCallbackPtr;
	return true;
}

static int64_t lcNanoseconds(void) {
	struct timespec now;
	clock_gettime(CLOCK_MONOTONIC, &now);
	return (int64_t) now.tv_sec * 1000000000LL + now.tv_nsec;
}

/* Take every committed container out of the ring buffer, count its events and free it. */
static void lcDrain(davisCommonHandle handle, atomic_uint_fast32_t *running, int64_t *counts) {
	caerEventPacketContainer container;
	while ((container = dataExchangeGet(&handle->state.dataExchange, running)) != NULL) {
		caerEventPacketHeader polarity = caerEventPacketContainerGetEventPacket(container, POLARITY_EVENT);
		caerEventPacketHeader special  = caerEventPacketContainerGetEventPacket(container, SPECIAL_EVENT);
		if (polarity != NULL) {
			counts[0] += caerEventPacketHeaderGetEventValid(polarity);
		}
		if (special != NULL) {
			counts[1] += caerEventPacketHeaderGetEventValid(special);
		}
		caerEventPacketContainerFree(container);
	}
}

int lc_run(const uint8_t *data, size_t nBytes, size_t transferBytes, int64_t *out) {
	struct davis_common_handle *handle = calloc(1, sizeof(struct davis_common_handle));
	if (handle == NULL) {
		return -1;
	}
	davisCommonState state = &handle->state;
	dataExchangeSettingsInit(&state->dataExchange);
	containerGenerationSettingsInit(&state->container);
	atomic_store(&state->deviceLogLevel, caerLogLevelGet());
	handle->deviceType         = CAER_DEVICE_DAVIS;
	handle->info.deviceID      = 1;
	handle->info.deviceString  = "libcaer translator benchmark";
	handle->info.dvsSizeX      = 346;
	handle->info.dvsSizeY      = 260;
	handle->info.apsSizeX      = 346;
	handle->info.apsSizeY      = 260;
	handle->info.apsColorFilter = MONO;
	davisCommonInit(handle);
	if (!davisCommonDataStart(handle, NULL, NULL, NULL)) {
		free(handle);
		return -1;
	}
	atomic_uint_fast32_t running = THR_RUNNING;
	int64_t counts[2]            = {0, 0};
	int64_t translatorNs         = 0;
	for (size_t pos = 0; pos < nBytes; pos += transferBytes) {
		size_t size   = (nBytes - pos < transferBytes) ? (nBytes - pos) : transferBytes;
		int64_t start = lcNanoseconds();
		davisCommonEventTranslator(handle, data + pos, size, &running);
		translatorNs += lcNanoseconds() - start;
		lcDrain(handle, &running, counts);
	}
	/* events still in the packets being filled (libcaer would commit them with the next container) */
	out[0] = counts[0] + state->currentPackets.polarityPosition;
	out[1] = counts[1] + state->currentPackets.specialPosition;
	davisCommonDataStop(handle);
	free(handle);
	out[2] = translatorNs;
	return 0;
}
