// The client's side of the session core (protocol/session.py ClientSession) in the page, with the same rules:
// after connecting, after a gap in the server's frame ids and after dropped frames, wait for a self-contained
// frame (skipping dependent ones); ask for a reference only with evidence that one is needed, at most every
// referenceTimeout seconds while the need lasts. Events in, decisions out; times are seconds on the page clock.

export class ClientSession {
  constructor(referenceTimeout = 1.5) {
    this.referenceTimeout = referenceTimeout;
    this.counters = { framesArrived: 0, framesReceived: 0, framesApplied: 0, framesRejected: 0, framesSkipped: 0,
                      framesLost: 0, referenceRequests: 0, rejections: [] };
    this.awaitingSelfContained = true;
    this.needsReference = false;
    this.lastFrameId = null;
    this._lastRequest = null;
    this._evidence = "";
  }

  // A frame's last byte arrived (before it is decoded or applied): the report to send the server at once, as
  // [[frameId, bytes, now]] (a ReceiveReport's entries; its rate controller times the link with them).
  frameArrived(now, frameId, sizeBytes) {
    this.counters.framesArrived++;
    return [[frameId, sizeBytes, now]];
  }

  // What the page sends right after it connects: an empty report ("this client reports arrivals").
  announceReports() {
    return [];
  }

  connected(now) {
    this.awaitingSelfContained = true;
    this.lastFrameId = null;
  }

  // A frame arrived: true to apply it, false to skip it.
  frameReceived(now, frameId, selfContained) {
    const c = this.counters;
    c.framesReceived++;
    if (this.lastFrameId !== null && frameId > this.lastFrameId + 1) {
      c.framesLost += frameId - this.lastFrameId - 1;
      this.awaitingSelfContained = true;
    }
    this.lastFrameId = this.lastFrameId === null ? frameId : Math.max(this.lastFrameId, frameId);
    if (this.awaitingSelfContained && !selfContained) {
      c.framesSkipped++;
      this._evidence = this._evidence || "waiting for a self-contained frame";
      return false;
    }
    return true;
  }

  // The page applied (or rejected, with reason) a frame; needsReference is its own state. Returns a reason to
  // send a ReferenceRequest with, or null.
  frameProcessed(now, applied, needsReference, reason = "") {
    const c = this.counters;
    if (applied) {
      c.framesApplied++;
      this.awaitingSelfContained = false;
    } else {
      c.framesRejected++;
      if (c.rejections.length < 8) c.rejections.push(reason);
      this._evidence = this._evidence || reason || "frame rejected";
    }
    this.needsReference = needsReference;
    if (needsReference) this._evidence = this._evidence || "reference missing";
    return this.tick(now);
  }

  framesDropped(now, count, reason = "frames dropped before processing") {
    this.counters.framesSkipped += count;
    this.awaitingSelfContained = true;
    this._evidence = this._evidence || reason;
  }

  tick(now) {
    if (!(this.needsReference || this.awaitingSelfContained)) {
      this._evidence = "";
      this._lastRequest = null;
      return null;
    }
    if (!this._evidence) return null;
    if (this._lastRequest !== null && now - this._lastRequest < this.referenceTimeout) return null;
    this._lastRequest = now;
    this.counters.referenceRequests++;
    const reason = this._evidence;
    this._evidence = "";
    return reason;
  }
}
