// The H.264 atlas in the page: each frame's Annex-B access unit (IDRs carry SPS and PPS in-band, as
// codec/encoder.py makes them) goes to a WebCodecs VideoDecoder with the frame id as its timestamp, so every
// decoded picture comes back paired with its quad frame by frame id. The decoder is configured from the SPS
// of the first IDR (codec string avc1.PPCCLL: profile, constraint flags, level -- x264's ultrafast preset makes
// Constrained Baseline), and again whenever a later IDR's SPS differs. As codec/decoder.py's AtlasDecoder,
// it waits for an IDR at the start, after any error and after a gap in the frame ids (a P-frame must follow
// the picture it predicts from).

// NAL unit types of an Annex-B access unit.
export function nalUnits(data) {
  const units = [];
  for (let i = 0; i + 3 < data.length; i++) {
    if (data[i] === 0 && data[i + 1] === 0 && data[i + 2] === 1) {
      units.push({ type: data[i + 3] & 0x1f, start: i + 3 });
      i += 2;
    }
  }
  return units;
}

export const NAL_IDR = 5, NAL_SPS = 7;

export function isIdr(data) {
  return nalUnits(data).some((u) => u.type === NAL_IDR);
}

// avc1.PPCCLL from the access unit's SPS (profile_idc, constraint flags, level_idc), or null without one.
export function codecString(data) {
  const sps = nalUnits(data).find((u) => u.type === NAL_SPS);
  if (!sps || sps.start + 4 > data.length) return null;
  const hex = (b) => b.toString(16).padStart(2, "0").toUpperCase();
  return `avc1.${hex(data[sps.start + 1])}${hex(data[sps.start + 2])}${hex(data[sps.start + 3])}`;
}

export class AtlasVideo {
  // onPicture(frameId, videoFrame) owns the VideoFrame (must close it); onError(message).
  constructor(onPicture, onError) {
    this.onPicture = onPicture;
    this.onError = onError;
    this.decoder = null;
    this.codec = null;
    this.needsKeyframe = true;
    this.lastSequence = null;
  }

  get queued() {
    return this.decoder ? this.decoder.decodeQueueSize : 0;
  }

  _make(codec) {
    this.close();
    const decoder = new VideoDecoder({
      output: (frame) => this.onPicture(frame.timestamp, frame),
      error: (e) => {
        if (this.decoder === decoder) {
          this.decoder = null;
          this.needsKeyframe = true;
          this.onError(`H.264 decoder: ${e.message || e}`);
        }
      },
    });
    decoder.configure({ codec, optimizeForLatency: true, hardwareAcceleration: "no-preference" });
    this.decoder = decoder;
    this.codec = codec;
  }

  // Submit one access unit; returns "" when it went to the decoder, else why not (the frame is then unusable
  // and the caller needs a self-contained frame).
  decode(frameId, data) {
    const key = isIdr(data);
    if (key) {
      const codec = codecString(data);
      if (!codec) return `frame ${frameId}: IDR without an SPS`;
      if (!this.decoder || codec !== this.codec) this._make(codec);
      this.needsKeyframe = false;
    } else if (this.needsKeyframe || !this.decoder) {
      return `frame ${frameId}: the video decoder is waiting for a keyframe`;
    } else if (this.lastSequence !== null && frameId !== this.lastSequence + 1) {
      this.needsKeyframe = true;
      return `frame ${frameId}: video frame ${this.lastSequence + 1} is missing; waiting for a keyframe`;
    }
    this.lastSequence = frameId;
    try {
      this.decoder.decode(new EncodedVideoChunk({ type: key ? "key" : "delta", timestamp: frameId, data }));
    } catch (e) {
      this.needsKeyframe = true;
      return `frame ${frameId}: ${e.message || e}`;
    }
    return "";
  }

  // Forget everything (a new session, an overflow): pictures still in the decoder are dropped (a new session's
  // frame ids start again at 0) and the next one must come from an IDR.
  reset() {
    this.close();
    this.needsKeyframe = true;
    this.lastSequence = null;
  }

  close() {
    if (this.decoder && this.decoder.state !== "closed") this.decoder.close();
    this.decoder = null;
    this.codec = null;
  }
}
